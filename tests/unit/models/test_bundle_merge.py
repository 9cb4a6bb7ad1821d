"""merge_bundles / `n3dmap bundle merge`: bundles trained apart joined into one, checked tensor by tensor
against the source bundles; equal copies kept once; differing copies refused unless --take says which; a
module that reads another mapper is named; presets must agree."""

import pytest
import torch

from core.bundle import foreign_mapper_readers, load_bundle, merge_bundles, save_bundle
from core.errors import BundleError
from core.models.registry import build_module
from core.presets import SMALL, TINY
from core.tasks import build_task
from services.cli.main import main


def _flow_bundle(path, seed: int, preset=TINY):
    """mapper + flow over its features (the benchmark's flow stage bundle), weights from `seed`."""
    torch.manual_seed(seed)
    task = build_task("flow", preset, inputs="features", seed=seed)
    modules = {"mapper": task.mapper, "flow": task.flow}
    return save_bundle(path, modules=modules, preset=preset, provenance={"task": "flow", "seed": seed})


def _egomotion_bundle(path, seed: int):
    torch.manual_seed(seed)
    task = build_task("egomotion", TINY, seed=seed)
    return save_bundle(path, modules={"egomotion": task.egomotion}, preset=TINY, provenance={"task": "egomotion"})


def _state(bundle_dir, name):
    """One module's tensors as stored in a bundle's weights file (the slow, obvious reference)."""
    from safetensors.torch import load_file

    tensors = load_file(str(bundle_dir / "weights.safetensors"))
    return {k[len(name) + 1:]: v for k, v in tensors.items() if k.startswith(name + ".")}


def _assert_same_tensors(merged_dir, source_dir, name):
    merged, source = _state(merged_dir, name), _state(source_dir, name)
    assert merged.keys() == source.keys() and merged
    for key in source:
        assert torch.equal(merged[key], source[key]), (name, key)


def test_union_of_disjoint_bundles_keeps_every_tensor(tmp_path):
    flow, ego = _flow_bundle(tmp_path / "flow", 0), _egomotion_bundle(tmp_path / "ego", 1)
    bundles = [load_bundle(flow), load_bundle(ego)]
    modules, sources = merge_bundles(bundles)
    assert sources == {"mapper": 0, "flow": 0, "egomotion": 1}
    out = save_bundle(tmp_path / "merged", modules=modules, preset=TINY)
    assert set(load_bundle(out).modules) == {"mapper", "flow", "egomotion"}
    for name, src in (("mapper", flow), ("flow", flow), ("egomotion", ego)):
        _assert_same_tensors(out, src, name)


def test_equal_copies_are_kept_once_and_differing_ones_need_take(tmp_path):
    a, same = _flow_bundle(tmp_path / "a", 0), _flow_bundle(tmp_path / "same", 0)
    other = _flow_bundle(tmp_path / "other", 5)
    modules, sources = merge_bundles([load_bundle(a), load_bundle(same)])
    assert sources == {"mapper": 0, "flow": 0}
    with pytest.raises(BundleError, match="'flow' differs.*--take flow=B") as err:
        merge_bundles([load_bundle(a), load_bundle(other)])
    assert str(tmp_path / "other") in str(err.value)
    bundles = [load_bundle(a), load_bundle(other)]
    _, sources = merge_bundles(bundles, take={"mapper": 1, "flow": 1})
    assert sources == {"mapper": 1, "flow": 1}
    with pytest.raises(BundleError, match="no bundle holds a module 'detector'"):
        merge_bundles(bundles, take={"mapper": 1, "flow": 1, "detector": 0})


def test_a_module_kept_beside_another_mapper_is_named(tmp_path):
    a, other = _flow_bundle(tmp_path / "a", 0), _flow_bundle(tmp_path / "other", 5)
    bundles = [load_bundle(a), load_bundle(other)]
    # Flow from a, mapper from other: a's flow reads features of a mapper it was not trained on.
    _, sources = merge_bundles(bundles, take={"mapper": 1, "flow": 0})
    assert foreign_mapper_readers(bundles, sources) == ["flow"]
    assert foreign_mapper_readers(bundles, {"mapper": 0, "flow": 0}) == []
    # An occupancy head also reads the mapper; egomotion does not.
    torch.manual_seed(3)
    occ = save_bundle(tmp_path / "occ", preset=TINY, modules={
        "mapper": bundles[1].modules["mapper"],
        "occupancy": build_module("occupancy_head", {"in_channels": TINY.feature_dim})})
    ego = _egomotion_bundle(tmp_path / "ego", 2)
    three = [bundles[0], load_bundle(occ), load_bundle(ego)]
    _, sources = merge_bundles(three, take={"mapper": 0})
    assert foreign_mapper_readers(three, sources) == ["occupancy"]


def test_presets_must_agree(tmp_path):
    tiny = _flow_bundle(tmp_path / "tiny", 0)
    small = save_bundle(tmp_path / "small", preset=SMALL,
                        modules={"occupancy": build_module("occupancy_head", {"in_channels": SMALL.feature_dim})})
    with pytest.raises(BundleError, match="different presets"):
        merge_bundles([load_bundle(tiny), load_bundle(small)])
    with pytest.raises(BundleError, match="at least two"):
        merge_bundles([load_bundle(tiny)])


def test_cli_merges_and_refuses_by_name(tmp_path, capsys):
    flow, other = _flow_bundle(tmp_path / "flow", 0), _flow_bundle(tmp_path / "other", 5)
    ego = _egomotion_bundle(tmp_path / "ego", 1)
    out = tmp_path / "merged"
    assert main(["bundle", "merge", str(flow), str(ego), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"egomotion  from {ego}" in printed and f"mapper     from {flow}" in printed
    merged = load_bundle(out)
    assert merged.meta["provenance"]["task"] == "merge"
    assert merged.meta["provenance"]["sources"] == {"egomotion": str(ego), "flow": str(flow), "mapper": str(flow)}
    assert len(merged.meta["provenance"]["parents"]) == 2
    _assert_same_tensors(out, ego, "egomotion")
    before = (out / "weights.safetensors").read_bytes()

    assert main(["bundle", "merge", str(flow), str(ego), "--out", str(out)]) == 2       # never overwrites
    assert "already holds a bundle" in capsys.readouterr().err
    assert (out / "weights.safetensors").read_bytes() == before
    assert main(["bundle", "merge", str(flow), str(other), "--out", str(tmp_path / "m2")]) == 2
    assert "'flow' differs" in capsys.readouterr().err
    assert main(["bundle", "merge", str(flow), str(other), "--out", str(tmp_path / "m2"),
                 "--take", f"flow={tmp_path / 'nowhere'}"]) == 2
    assert "is not one of the bundles given" in capsys.readouterr().err
    assert main(["bundle", "merge", str(flow), str(other), "--out", str(tmp_path / "m2"), "--take", "flow"]) == 2
    assert "expected MODULE=B" in capsys.readouterr().err
    assert not (tmp_path / "m2" / "bundle.json").exists()
    assert main(["bundle", "merge", str(flow), str(other), "--out", str(tmp_path / "m3"),
                 "--take", f"mapper={other}", "--take", f"flow={flow}"]) == 0
    assert "warning: flow" in capsys.readouterr().out
    assert main(["bundle", "info", str(out)]) == 0
    assert "merge" in capsys.readouterr().out
