"""Bundle round trip (save -> load gives identical outputs), typed errors, map_frames over a bundle."""

import json

import pytest
import torch

from core.bundle import load_bundle, merged_modules, read_bundle_meta, save_bundle
from core.errors import BundleError
from core.geometry.grid import GridConfig
from core.models.latent_map import masked_average
from core.models.net2d import Net2D
from core.pipeline import map_frames
from core.pipeline.map import heightmap_from_occupancy
from core.presets import TINY
from core.tasks import build_task


@pytest.fixture(scope="module")
def bundle_dir(tmp_path_factory):
    torch.manual_seed(0)
    task = build_task("pretrain", TINY, objective="contrastive", seed=0)
    # move BatchNorm running stats off their defaults so the round trip must carry buffers too
    for m in task.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    path = tmp_path_factory.mktemp("bundle")
    save_bundle(path, modules=task.exported_modules(), preset=TINY,
                provenance={"task": "pretrain", "objective": "contrastive"}, metrics={"loss": torch.tensor(1.5)})
    return path, {k: v.eval() for k, v in task.exported_modules().items()}


def test_round_trip_gives_identical_outputs(bundle_dir, make_views):
    path, originals = bundle_dir
    bundle = load_bundle(path)
    assert set(bundle.modules) == {"mapper", "projector", "net2d", "occupancy"}
    assert bundle.preset == TINY and bundle.meta["metrics"]["loss"] == 1.5
    assert all(not m.training for m in bundle.modules.values())
    rgb, depth, K, cam_T_ref = make_views(1, 2, 16, 48, TINY.grid)
    with torch.no_grad():
        for name in ("mapper",):
            assert torch.equal(originals[name](rgb, depth, K, cam_T_ref), bundle.modules[name](rgb, depth, K, cam_T_ref))
        image = torch.rand(1, 3, 16, 48)
        assert torch.equal(originals["net2d"](image), bundle.modules["net2d"](image))
        feat = torch.randn(1, TINY.feature_dim, *TINY.grid.shape_zyx)
        assert torch.equal(originals["occupancy"](feat), bundle.modules["occupancy"](feat))
        assert torch.equal(originals["projector"](feat, K[:, 0], cam_T_ref[:, 0], 16, 48),
                           bundle.modules["projector"](feat, K[:, 0], cam_T_ref[:, 0], 16, 48))


def test_bundle_json_names_modules_and_params(bundle_dir):
    meta = json.loads((bundle_dir[0] / "bundle.json").read_text())
    assert meta["modules"]["mapper"]["kind"] == "mapper"
    assert meta["modules"]["net2d"]["params"] == sum(p.numel() for p in bundle_dir[1]["net2d"].parameters())
    assert meta["grid"] == TINY.grid.to_dict() and meta["provenance"]["objective"] == "contrastive"


def _copy(src, dst):
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def test_missing_and_truncated_weights_raise_bundle_error(bundle_dir, tmp_path):
    missing = _copy(bundle_dir[0], tmp_path / "missing")
    (missing / "weights.safetensors").unlink()
    with pytest.raises(BundleError, match="weights.safetensors"):
        load_bundle(missing)
    truncated = _copy(bundle_dir[0], tmp_path / "truncated")
    data = (truncated / "weights.safetensors").read_bytes()
    (truncated / "weights.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(BundleError):
        load_bundle(truncated)
    with pytest.raises(BundleError, match="bundle.json"):
        load_bundle(tmp_path / "nowhere")


def test_missing_module_and_shape_mismatch_raise_bundle_error(bundle_dir, tmp_path):
    with pytest.raises(BundleError, match="egomotion"):
        load_bundle(bundle_dir[0], only=["egomotion"])
    with pytest.raises(BundleError, match="egomotion"):
        load_bundle(bundle_dir[0]).require("egomotion")
    bad = _copy(bundle_dir[0], tmp_path / "bad")
    meta = json.loads((bad / "bundle.json").read_text())
    meta["modules"]["net2d"]["config"]["out_channels"] += 1
    (bad / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(BundleError, match="shape"):
        load_bundle(bad)


def test_merge_adds_modules_and_keeps_parent(bundle_dir, tmp_path):
    parent = load_bundle(bundle_dir[0])
    extra = Net2D(widths=(4, 8), out_channels=3)
    with pytest.raises(BundleError, match="already"):
        merged_modules(parent, {"net2d": extra})
    modules = merged_modules(parent, {"extra2d": extra})
    save_bundle(tmp_path / "child", modules=modules, preset=parent.preset, provenance={"parents": [parent.path]})
    child = load_bundle(tmp_path / "child")
    assert set(child.modules) == set(parent.modules) | {"extra2d"}
    assert read_bundle_meta(tmp_path / "child")["provenance"]["parents"] == [parent.path]


def test_map_frames_matches_modules(bundle_dir, make_views):
    bundle = load_bundle(bundle_dir[0])
    rgb, depth, K, cam_T_ref = make_views(1, 2, 16, 48, TINY.grid)
    world_T_cam = torch.linalg.inv(cam_T_ref)  # world = ref here
    out = map_frames(bundle, rgb, depth, K, world_T_cam, torch.eye(4)[None])
    with torch.no_grad():
        feats, in_view, _ = bundle.modules["mapper"].encode_views(rgb, depth, K, cam_T_ref)
        expected = masked_average(feats, in_view)
    assert torch.allclose(out["features"], expected, atol=1e-5)
    assert out["occupancy"].shape == (1, 1, *TINY.grid.shape_zyx)
    assert out["heightmap"].shape == (1, TINY.grid.Z, TINY.grid.X)


def test_heightmap_matches_loop():
    grid = GridConfig(xmin=0, xmax=3, ymin=0, ymax=4, zmin=0, zmax=2, Z=2, Y=4, X=3)
    occ = torch.rand(1, 1, 2, 4, 3)
    hm = heightmap_from_occupancy(occ, grid)
    for z in range(2):
        for x in range(3):
            ys = [y for y in range(4) if occ[0, 0, z, y, x] >= 0.5]
            ref = (grid.ymax - (grid.ymin + min(ys) * grid.voxel_size)) if ys else 0.0
            assert hm[0, z, x].item() == pytest.approx(ref)


def test_a_malformed_bundle_json_is_refused_by_name(bundle_dir, tmp_path):
    good = json.loads((bundle_dir[0] / "bundle.json").read_text())
    name = next(iter(good["modules"]))
    cases = [([1, 2], "not a JSON object"),
             ({**good, "modules": [name]}, "'modules' must map a module name"),
             ({**good, "modules": {name: {"kind": good["modules"][name]["kind"]}}}, rf"module '{name}' needs a 'kind'"),
             ({**good, "modules": {name: {**good["modules"][name], "kind": "bogus"}}},
              rf"bundle .*: module '{name}' in bundle.json: unknown module kind 'bogus'")]
    for i, (meta, message) in enumerate(cases):
        bad = _copy(bundle_dir[0], tmp_path / f"bad{i}")
        (bad / "bundle.json").write_text(json.dumps(meta))
        with pytest.raises(BundleError, match=message):
            load_bundle(bad)
