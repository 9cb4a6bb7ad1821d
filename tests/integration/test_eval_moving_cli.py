"""`n3dmap eval moving|retrieval|detection|all` as real processes on a tiny generated dataset.

The bundle holds freshly initialised modules: the commands are under test, not the training, so the
checks are what the reports say — files, metrics.json keys and value ranges, ground-truth counts
against loops written here, each table named in report.md — plus `eval detection --pred --gt` on
KITTI files with an AP computed by hand, and bad paths exiting 2 with one line.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from core.bundle import save_bundle
from core.data.ground_truth import points_in_ref
from core.data.shards import write_dataset
from core.eval.kitti_labels import FrameLabels, write_label_file
from core.geometry import se3
from core.geometry.boxes import points_in_boxes, transform_boxes
from core.presets import TINY
from core.synthetic import generate_record
from core.tasks.detector import DetectorTask
from core.tasks.egomotion import EgomotionTask
from core.tasks.flow import FlowTask
from core.tasks.pretrain import PretrainTask
from services.cli.main import main

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration
GRID = TINY.grid


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Two records (static rig, moving rig); a bundle without a detector and one with."""
    root = tmp_path_factory.mktemp("eval_moving")
    records = [generate_record(TINY, seed=11, moving_ego=False), generate_record(TINY, seed=12, moving_ego=True)]
    write_dataset(root / "data", records, split="test", preset_name="tiny", grid=GRID.to_dict(),
                  generator={"moving_ego": [False, True]}, seed=11, shard_bytes=1 << 30)
    torch.manual_seed(0)
    modules = dict(PretrainTask.from_preset(TINY).exported_modules())
    modules.update(flow=FlowTask.from_preset(TINY).flow, egomotion=EgomotionTask.from_preset(TINY).egomotion)
    save_bundle(root / "bundle", modules=modules, preset=TINY, provenance={"test": True}, metrics={})
    modules["detector"] = DetectorTask.from_preset(TINY).detector
    save_bundle(root / "bundle_det", modules=modules, preset=TINY, provenance={"test": True}, metrics={})
    return root, records


def _cli(*args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "services.cli.main", "eval", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return proc


def _moving_gt_count(record, t: int, min_points: int = 10) -> int:
    """Slow reference: moving objects valid at t and t+1, centred in the grid, hit by ≥ min_points points."""
    xyz, ok = points_in_ref(record, t)
    pts = xyz.double().reshape(-1, 3)[ok.reshape(-1)]
    ref_T_world = se3.invert(torch.as_tensor(record["world_T_ref"][t], dtype=torch.float64))
    count = 0
    for k in range(record["boxes"].shape[1]):
        if not (record["box_moving"][k] and record["box_valid"][t, k] and record["box_valid"][t + 1, k]):
            continue
        box = transform_boxes(ref_T_world[None], torch.as_tensor(record["boxes"][t, k], dtype=torch.float64)[None, None])[0, 0]
        centre_in = all(lo <= float(c) < hi for c, lo, hi in zip(box[:3], GRID.bounds_min, GRID.bounds_max))
        hits = int(points_in_boxes(pts[None], box[None, None])[0, :, 0].sum())
        count += int(centre_in and hits >= min_points)
    return count


def _in_unit(x) -> bool:
    return x is None or 0.0 <= x <= 1.0


def test_eval_all_runs_every_allowed_kind_and_skips_detection(setup):
    root, records = setup
    out = root / "all"
    proc = _cli("all", "--data", str(root / "data"), "--bundle", str(root / "bundle"), "--out", str(out),
                "--device", "cpu")
    assert "skipped detection" in proc.stdout
    payload = json.loads((out / "metrics.json").read_text())
    assert set(payload["metrics"]) == {"retrieval", "moving", "egomotion", "flow", "occupancy"}
    assert "detector" in payload["skipped"]["detection"]
    report = (out / "report.md").read_text()
    for heading in ("## Retrieval", "## Moving", "## Egomotion", "## Flow", "## Occupancy",
                    "### Static camera", "### Moving camera", "detection**: skipped"):
        assert heading in report
    assert "(moving/moving_pr_static_iou05.png)" in report and (out / "moving" / "moving_pr_static_iou05.png").is_file()

    # moving objects: one pair per camera setting, every method, APs in [0, 1], GT counted by a loop
    moving = payload["metrics"]["moving"]
    assert moving["moving_pairs"] == {"static": 1, "moving": 1}
    for cam, record in zip(("static", "moving"), records):
        methods = moving["moving"][cam]
        assert set(methods) == {"3d (model)", "oracle 3d flow", "2.5d farneback", "2.5d farneback, stabilised",
                                "2.5d oracle 2d flow", "2.5d oracle 2d flow, stabilised"}
        for m in methods.values():
            assert set(m["ap3d"]) == {"0.25", "0.33", "0.5"} and all(_in_unit(v) for v in m["ap3d"].values())
            assert m["num_gt"] == _moving_gt_count(record, 0)
        # a static rig makes stabilisation a no-op for the 2.5D baseline
        if cam == "static":
            assert methods["2.5d oracle 2d flow"] == methods["2.5d oracle 2d flow, stabilised"]
    # the oracle 3D flow finds moving cars where there are some (an upper bound that is not vacuous)
    if moving["moving"]["static"]["oracle 3d flow"]["num_gt"]:
        assert moving["moving"]["static"]["oracle 3d flow"]["ap3d"]["0.25"] > 0.5

    # retrieval: 2 records × 2 steps × 10 pairs, P@K in [0, 1] and non-decreasing in K
    ret = payload["metrics"]["retrieval"]["retrieval"]
    for kind in ("2d", "3d"):
        s = ret[kind]
        assert s["queries"] == 40
        assert 0.0 <= s["p@1"] <= s["p@5"] <= s["p@10"] <= 1.0
    assert "| 2D patches" in report and "| 3D feature cubes" in report


def test_eval_detection_on_a_dataset(setup):
    root, records = setup
    out = root / "det"
    proc = _cli("detection", "--data", str(root / "data"), "--bundle", str(root / "bundle_det"), "--out", str(out),
                "--device", "cpu", "--max-records", "1", "--iou", "0.6")
    assert "AP3D@0.5" in proc.stdout
    e = json.loads((out / "metrics.json").read_text())["metrics"]["detection"]["object"]
    assert set(e["ap3d"]) == set(e["apbev"]) == {"0.33", "0.5", "0.6", "0.75"}
    assert all(_in_unit(v) for v in [*e["ap3d"].values(), *e["apbev"].values()])
    # ground truth: every valid box of record 0 at each step whose centre lies in the grid (a loop)
    rec = records[0]
    expected = 0
    for t in range(rec["boxes"].shape[0]):
        ref_T_world = np.linalg.inv(rec["world_T_ref"][t].astype(np.float64))
        for k in np.flatnonzero(rec["box_valid"][t]):
            c = ref_T_world[:3, :3] @ rec["boxes"][t, k, :3] + ref_T_world[:3, 3]
            expected += all(lo <= v < hi for v, lo, hi in zip(c, GRID.bounds_min, GRID.bounds_max))
    assert e["num_gt"] == expected
    assert "| object |" in (out / "report.md").read_text() and (out / "detection_pr.png").is_file()


CAR = np.array([2.0, 1.0, 15.0, 4.0, 1.5, 2.0, 0.0])  # canonical box in cam, yaw 0: lx = 4 along x


def _shifted(box, dx):
    b = box.copy()
    b[0] += dx
    return b


def _write(directory: Path, frame: str, boxes, scores=None):
    directory.mkdir(exist_ok=True)
    write_label_file(str(directory / f"{frame}.txt"),
                     FrameLabels(types=["Car"] * len(boxes), boxes_cam=np.array(boxes).reshape(-1, 7), scores=scores))


def _all_point_ap(tp: list[bool], num_gt: int) -> float:
    """Slow reference: VOC all-point AP of detections already sorted by score."""
    hits = np.cumsum(tp)
    precision = hits / np.arange(1, len(tp) + 1)
    recall = hits / num_gt
    ap, prev = 0.0, 0.0
    for i, r in enumerate(recall):
        ap += (r - prev) * precision[i:].max()
        prev = r
    return ap


def test_eval_detection_kitti_files_hand_computed(tmp_path):
    gt, pred, out = tmp_path / "gt", tmp_path / "pred", tmp_path / "report"
    far = _shifted(CAR, 8.0)
    _write(gt, "000000", [CAR, far])
    _write(gt, "000001", [CAR])
    # frame 0: the first car exact (0.9), a box 20 m from anything (0.8), the far car shifted 1.6 m
    # along its length (0.6); frame 1: its car exact (0.7)
    _write(pred, "000000", [CAR, _shifted(CAR, -20.0), _shifted(far, 1.6)], scores=np.array([0.9, 0.8, 0.6]))
    _write(pred, "000001", [CAR], scores=np.array([0.7]))
    code = main(["eval", "detection", "--pred", str(pred), "--gt", str(gt), "--out", str(out)])
    assert code == 0
    m = json.loads((out / "metrics.json").read_text())["detection"]["Car"]
    shifted_iou = (4.0 - 1.6) / (4.0 + 1.6)  # same-size boxes overlapping along x: 3D and BEV alike
    assert 0.33 < shifted_iou < 0.5
    # sorted by score: exact (TP), stray (FP), exact (TP), shifted (TP only at IoU ≤ 0.4286)
    for key, threshold in (("0.33", 0.33), ("0.5", 0.5), ("0.75", 0.75)):
        expected = _all_point_ap([True, False, True, shifted_iou >= threshold], num_gt=3)
        assert m["ap3d"][key] == pytest.approx(expected, abs=1e-9)
        assert m["apbev"][key] == pytest.approx(expected, abs=1e-9)
    assert m["ap3d"]["0.33"] == pytest.approx(1 / 3 + 2 * (1 / 3) * 0.75)
    assert m["ap3d"]["0.5"] == pytest.approx(5 / 9)


@pytest.mark.parametrize("argv, needle", [
    (["eval", "moving", "--data", "/nonexistent/data", "--bundle", "/nonexistent/b", "--out", "/tmp/x"], "/nonexistent/"),
    (["eval", "retrieval", "--data", "/nonexistent/data", "--bundle", "/nonexistent/b", "--out", "/tmp/x"], "/nonexistent/"),
    (["eval", "all", "--data", "/nonexistent/data", "--bundle", "/nonexistent/b", "--out", "/tmp/x"], "/nonexistent/"),
    (["eval", "detection", "--pred", "/nonexistent/p", "--gt", "/nonexistent/g", "--out", "/tmp/x"], "--pred /nonexistent/p"),
    (["eval", "detection", "--out", "/tmp/x"], "--pred DIR --gt DIR"),
    (["eval", "detection", "--pred", "/tmp", "--data", "/tmp", "--out", "/tmp/x"], "not both"),
])
def test_bad_paths_exit_2_with_one_line(argv, needle, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err


def test_missing_bundle_exits_2(setup, capsys):
    root, _ = setup
    assert main(["eval", "moving", "--data", str(root / "data"), "--bundle", str(root / "nope"),
                 "--out", str(root / "x"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope" in err
