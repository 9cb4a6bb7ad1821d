"""Scoring KITTI label directories: metrics.json layout, hand-computed AP, missing and bad files."""

import json

import numpy as np
import pytest

from core.errors import DataError
from core.eval.kitti_labels import FrameLabels, write_label_file
from services.cli.eval_detection import run_detection_files_eval

CAR = np.array([2.0, 1.0, 15.0, 4.0, 1.5, 2.0, 0.3])
PED = np.array([-3.0, 1.0, 10.0, 0.6, 1.8, 0.6, 0.0])


def shifted(box, dx):
    b = box.copy()
    b[0] += dx
    return b


def write(directory, frame, types, boxes, scores=None):
    directory.mkdir(exist_ok=True)
    write_label_file(str(directory / f"{frame}.txt"),
                     FrameLabels(types=types, boxes_cam=np.array(boxes).reshape(-1, 7), scores=scores))


def test_metrics_layout_and_hand_computed_ap(tmp_path):
    gt, pred, out = tmp_path / "gt", tmp_path / "pred", tmp_path / "report"
    write(gt, "000000", ["Car", "Pedestrian", "DontCare"], [CAR, PED, np.zeros(7)])
    write(gt, "000001", ["Car"], [shifted(CAR, 5.0)])
    write(gt, "000002", ["Car"], [shifted(CAR, -5.0)])  # no prediction file for this frame
    # Frame 0: exact car (0.9), its duplicate (0.8), a car 7 m away from any (0.7); the pedestrian
    # exact. Frame 1: its car exact at 0.6. Frame 2: its car is missed.
    write(pred, "000000", ["Car", "Car", "Car", "Pedestrian"], [CAR, CAR, shifted(CAR, 7.0), PED],
          scores=np.array([0.9, 0.8, 0.7, 0.5]))
    write(pred, "000001", ["Car"], [shifted(CAR, 5.0)], scores=np.array([0.6]))
    metrics = run_detection_files_eval(str(pred), str(gt), str(out), ious=[0.7], classes=None)
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk == metrics
    assert sorted(metrics["detection"]) == ["Car", "Pedestrian"]  # DontCare is not a class
    car = metrics["detection"]["Car"]
    assert sorted(car["ap3d"]) == ["0.33", "0.5", "0.7", "0.75"] and sorted(car["apbev"]) == sorted(car["ap3d"])
    # Cars ranked TP (0.9), FP duplicate (0.8), FP far box (0.7), TP (0.6); 3 GT:
    # precision 1, 1/2, 1/3, 1/2 at recall 1/3, 1/3, 1/3, 2/3 → AP = 1/3 · 1 + 1/3 · 1/2.
    for key in car["ap3d"]:
        assert car["ap3d"][key] == pytest.approx(1 / 3 + 1 / 6)
        assert car["apbev"][key] == pytest.approx(1 / 3 + 1 / 6)
    assert car["num_gt"] == 3 and car["num_pred"] == 4
    assert metrics["detection"]["Pedestrian"]["ap3d"]["0.5"] == pytest.approx(1.0)
    assert any("no prediction file" in w for w in metrics["detection_meta"]["warnings"])
    report = (out / "report.md").read_text()
    assert "| Car | 3 | 4 |" in report and "0.500" in report
    assert (out / "pr_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_partial_overlap_separates_thresholds(tmp_path):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    write(gt, "a", ["Car"], [np.array([0, 1, 10, 4, 2, 2, 0.0])])
    # Shifted 1 m along its 4 m length: BEV and 3D IoU = 3/5, between 0.5 and 0.75.
    write(pred, "a", ["Car"], [np.array([1, 1, 10, 4, 2, 2, 0.0])], scores=np.array([0.5]))
    m = run_detection_files_eval(str(pred), str(gt), str(tmp_path / "out"), ious=None, classes=["Car", "Van"])
    assert m["detection"]["Car"]["ap3d"] == {"0.33": 1.0, "0.5": 1.0, "0.75": 0.0}
    assert m["detection"]["Van"]["ap3d"]["0.5"] is None  # no ground truth: undefined, not 0


def test_malformed_prediction_line_is_a_one_line_error(tmp_path):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    write(gt, "000000", ["Car"], [CAR])
    pred.mkdir()
    (pred / "000000.txt").write_text("Car 0 0 0 0 0 0 0 1.5 2 4 2 1.75 15 0.3 0.9\nCar 0 0 0 0 0 0 0 1.5 2 4 2 1.75 15 0.3\n")
    with pytest.raises(DataError, match=r"pred/000000\.txt:2: malformed KITTI label line") as e:
        run_detection_files_eval(str(pred), str(gt), str(tmp_path / "out"))
    assert "\n" not in str(e.value)
    with pytest.raises(DataError, match="label directory not found"):
        run_detection_files_eval(str(pred), str(tmp_path / "missing"), str(tmp_path / "out"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no ground-truth label files"):
        run_detection_files_eval(str(pred), str(tmp_path / "empty"), str(tmp_path / "out"))
