"""`n3dmap eval moving|flow|detection --rerun FILE.rrd`: the recordings read back and compared with what
the evaluation computes, recomputed here through the same pipeline functions (a freshly initialised
bundle on two tiny synthetic records; the CLI runs in-process through services.cli.main.main).

Checked per timeline entry: one entry per evaluated pair (frame for detection); the predicted boxes and
scores equal the pipeline's, the ground-truth boxes equal the protocol's; the flow arrows sit at the
voxels the documented rule selects and equal the true and the predicted flow there (× voxel size); the
occupancy points are the centres of the observed voxels; `rerun rrd verify` accepts each file.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("rerun")

import services.cli.main as cli_main  # noqa: E402
from core.bundle import load_bundle, save_bundle  # noqa: E402
from core.data.ground_truth import gt_flow, gt_occupancy  # noqa: E402
from core.data.shards import write_dataset  # noqa: E402
from core.moving.amodal import SizePrior  # noqa: E402
from core.eval.moving_protocol import gt_moving_boxes  # noqa: E402
from core.eval.protocols.inputs import pair_inputs, record_batch  # noqa: E402
from core.models.detector_boxes import aabb_to_boxes, boxes_to_aabb  # noqa: E402
from core.moving.ground import DEFAULT_MARGIN_VOXELS  # noqa: E402
from core.pipeline.detect import detect, detections_per_item  # noqa: E402
from core.pipeline.flow import estimate_flow  # noqa: E402
from core.pipeline.moving import MovingObjectsConfig, moving_objects  # noqa: E402
from core.presets import TINY  # noqa: E402
from core.synthetic import generate_record  # noqa: E402
from core.tasks.detector import DetectorTask, gt_boxes_ref  # noqa: E402
from core.tasks.egomotion import EgomotionTask  # noqa: E402
from core.tasks.flow import FlowTask  # noqa: E402
from core.tasks.pretrain import PretrainTask  # noqa: E402
from services.viz import rerun_paths as paths  # noqa: E402
from tests.rrd_reading import Recording, array, rerun_cli, yaw_from_quaternions  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.usefixtures("one_torch_thread")]
GRID = TINY.grid
VOXEL = GRID.voxel_size
MIN_FLOW, MAX_ARROWS = 0.1, 2000  # services.viz.rerun_eval defaults


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Two tiny records (static rig, moving rig) and a bundle of freshly initialised modules."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("eval_rerun")
    records = [generate_record(TINY, seed=11, moving_ego=False), generate_record(TINY, seed=12, moving_ego=True)]
    write_dataset(root / "data", records, split="val", preset_name="tiny", grid=GRID.to_dict(),
                  generator={"moving_ego": [False, True]}, seed=11, shard_bytes=1 << 30)
    torch.manual_seed(0)
    modules = dict(PretrainTask.from_preset(TINY).exported_modules())
    modules.update(flow=FlowTask.from_preset(TINY).flow, egomotion=EgomotionTask.from_preset(TINY).egomotion,
                   detector=DetectorTask.from_preset(TINY).detector)
    save_bundle(root / "bundle", modules=modules, preset=TINY, provenance={"test": True}, metrics={})
    torch.set_num_threads(before)
    return root, records, load_bundle(root / "bundle", "cpu")


def _eval(capsys, root, kind, *extra) -> Recording:
    rrd = root / f"{kind}.rrd"
    code = cli_main.main(["eval", kind, "--data", str(root / "data"), "--bundle", str(root / "bundle"),
                          "--out", str(root / f"report_{kind}"), "--device", "cpu", "--rerun", str(rrd), *extra])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert f"-> {rrd} (" in out and "open it with `rerun" in out
    assert rerun_cli("rrd", "verify", str(rrd)).returncode == 0
    return Recording(rrd)


def _voxels_of(origins: np.ndarray) -> np.ndarray:
    """N×3 arrow origins (ref metres, voxel centres) -> N×3 (z, y, x) indices: mem = (ref - min)/voxel - 0.5."""
    mem = (origins - np.array(GRID.bounds_min)) / VOXEL - 0.5
    assert np.allclose(mem, np.rint(mem), atol=1e-4), "arrows must start at voxel centres"
    return np.rint(mem).astype(int)[:, ::-1]


def _expected_voxels(occupied: np.ndarray, flows: list[np.ndarray]) -> np.ndarray:
    """The documented rule, written out: occupied voxels where a flow reaches MIN_FLOW, every k-th in C order."""
    keep = []
    for z, y, x in zip(*np.nonzero(occupied)):
        if any(np.sqrt((f[:, z, y, x] ** 2).sum()) >= MIN_FLOW for f in flows):
            keep.append((z, y, x))
    stride = max(1, -(-len(keep) // MAX_ARROWS))
    return np.array(keep[::stride], int).reshape(-1, 3)


def _check_arrows(rec, timeline, entry, occupied, flows_by_path):
    zyx = None
    for path, flow in flows_by_path.items():
        origins = array(rec.at(path, "Arrows3D:origins", timeline)[entry], 3)
        vectors = array(rec.at(path, "Arrows3D:vectors", timeline)[entry], 3)
        voxels = _voxels_of(origins)
        if zyx is None:
            zyx = voxels
            assert np.array_equal(zyx, _expected_voxels(occupied, list(flows_by_path.values())))
        assert np.array_equal(voxels, zyx), "true and predicted arrows share their voxels"
        assert np.allclose(vectors, flow[:, zyx[:, 0], zyx[:, 1], zyx[:, 2]].T * VOXEL, atol=1e-5), path
    return zyx


def _check_boxes(rec, path, timeline, entry, boxes, scores=None):
    centres = array(rec.at(path, "Boxes3D:centers", timeline)[entry], 3)
    assert len(centres) == len(boxes), (path, entry)
    assert np.allclose(centres, boxes[:, :3], atol=1e-4)
    assert np.allclose(array(rec.at(path, "Boxes3D:half_sizes", timeline)[entry], 3), boxes[:, 3:6] / 2, atol=1e-4)
    yaw = yaw_from_quaternions(rec.at(path, "Boxes3D:quaternions", timeline)[entry])
    assert np.allclose(np.angle(np.exp(1j * (yaw - boxes[:, 6]))), 0, atol=1e-4)
    if scores is not None:
        assert rec.at(path, "Boxes3D:labels", timeline)[entry] == [f"{s:.2f}" for s in scores]


def _check_occupancy(rec, timeline, entry, occupied):
    centres = array(rec.at(paths.OCCUPANCY, "Points3D:positions", timeline)[entry], 3)
    assert np.array_equal(_voxels_of(centres), np.argwhere(occupied))


def test_eval_moving_recording_holds_the_evaluated_boxes_and_flow(capsys, setup):
    root, records, bundle = setup
    rec = _eval(capsys, root, "moving", "--no-baselines", "--size-prior", "4.0", "2.0", "1.5")
    # the CLI's defaults, with the amodal boxes' prior given on the command line
    config = MovingObjectsConfig(ground_margin=DEFAULT_MARGIN_VOXELS, size_prior=SizePrior.from_size(4.0, 2.0, 1.5))
    entry, found, true = 0, 0, 0
    with torch.inference_mode():
        for r, record in enumerate(records):
            batch = record_batch(record, "cpu")
            for t in range(record["rgb"].shape[0] - 1):
                out = moving_objects(bundle, **pair_inputs(batch, t, t + 1), config=config)
                valid = out["valid"][0]
                boxes, scores = out["boxes"][0, valid].double().numpy(), out["scores"][0, valid].double().numpy()
                _check_boxes(rec, paths.BOXES_PRED, paths.PAIR, entry, boxes, scores)
                _check_boxes(rec, paths.BOXES_TRUE, paths.PAIR, entry, gt_moving_boxes(record, t, GRID))
                found, true = found + len(boxes), true + len(gt_moving_boxes(record, t, GRID))
                occupied = gt_occupancy(record, t, GRID)[0].numpy() > 0.5
                _check_occupancy(rec, paths.PAIR, entry, occupied)
                _check_arrows(rec, paths.PAIR, entry, occupied, {paths.FLOW_TRUE: gt_flow(record, t, GRID).numpy(),
                                                                 paths.FLOW_PRED: out["flow"][0].float().numpy()})
                assert rec.at(paths.EVAL_LOG, "TextLog:text", paths.PAIR)[entry][0].startswith(
                    f"entry {entry}: record {r}, t={t}→{t + 1}")
                entry += 1
    assert sorted(rec.at(paths.BOXES_PRED, "Boxes3D:centers", paths.PAIR)) == list(range(entry))
    assert entry == 2 and found > 0 and true > 0  # the comparisons above were not of empty lists


def test_eval_flow_recording_holds_the_true_and_predicted_flow(capsys, setup):
    root, records, bundle = setup
    rec = _eval(capsys, root, "flow")
    entry = 0
    with torch.inference_mode():
        for record in records:
            batch = record_batch(record, "cpu")
            for t in range(record["rgb"].shape[0] - 1):
                out = estimate_flow(bundle, **pair_inputs(batch, t, t + 1))
                occupied = gt_occupancy(record, t, GRID)[0].numpy() > 0.5
                _check_occupancy(rec, paths.PAIR, entry, occupied)
                zyx = _check_arrows(rec, paths.PAIR, entry, occupied,
                                    {paths.FLOW_TRUE: gt_flow(record, t, GRID).numpy(),
                                     paths.FLOW_PRED: out["flow"][0].float().numpy()})
                assert len(zyx) > 0
                entry += 1
    assert sorted(rec.at(paths.FLOW_PRED, "Arrows3D:vectors", paths.PAIR)) == list(range(entry))
    assert paths.BOXES_PRED not in rec.entities()


def test_eval_detection_recording_holds_the_detections_and_ground_truth(capsys, setup):
    root, records, bundle = setup
    rec = _eval(capsys, root, "detection")
    entry = 0
    with torch.inference_mode():
        for record in records:
            batch = record_batch(record, "cpu")
            batch.update({k: torch.as_tensor(np.asarray(record[k]))[None] for k in ("boxes", "box_valid")})
            batch["boxes"] = batch["boxes"].float()
            for t in range(record["rgb"].shape[0]):
                pred = detections_per_item(detect(bundle, batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"],
                                                  batch["world_T_cam"][:, t], batch["world_T_ref"][:, t]))[0]
                boxes_ref, keep = gt_boxes_ref(batch, t, GRID)
                gt = aabb_to_boxes(boxes_to_aabb(boxes_ref[0, keep[0]])).double().numpy()
                _check_boxes(rec, paths.BOXES_PRED, paths.FRAME, entry, pred["boxes"].double().numpy(),
                             pred["scores"].double().numpy())
                _check_boxes(rec, paths.BOXES_TRUE, paths.FRAME, entry, gt)
                _check_occupancy(rec, paths.FRAME, entry, gt_occupancy(record, t, GRID)[0].numpy() > 0.5)
                entry += 1
    assert sorted(rec.at(paths.BOXES_TRUE, "Boxes3D:centers", paths.FRAME)) == list(range(entry)) == [0, 1, 2, 3]
    for v in range(records[0]["rgb"].shape[1]):
        assert len(rec.at(paths.camera_image(v, paths.REF), "Image:buffer", paths.FRAME)) == entry


def test_rerun_option_errors_are_one_line(capsys, setup, tmp_path):
    root, _, _ = setup
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for kind, extra, fragment in (("moving", ["--rerun", str(blocker / "x.rrd")], str(blocker / "x.rrd")),
                                  ("flow", ["--rerun", str(tmp_path)], "is a directory"),
                                  ("detection", ["--rerun", str(tmp_path / "x.rrd"), "--pred", str(tmp_path),
                                                 "--gt", str(tmp_path)], "--data/--bundle")):
        args = ["eval", kind, "--out", str(tmp_path / "r"), *extra]
        if kind != "detection":
            args += ["--data", str(root / "data"), "--bundle", str(root / "bundle")]
        code = cli_main.main(args)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith("n3dmap eval: error: ") and fragment in err[0], err
