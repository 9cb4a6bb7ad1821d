"""KITTI label files: round trip, bottom-centre conversion, malformed lines."""

import numpy as np
import pytest

from core.errors import DataError
from core.eval.kitti_labels import FrameLabels, read_label_dir, read_label_file, write_label_file

GT_LINE = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59\n"


def test_read_real_kitti_line(tmp_path):
    path = tmp_path / "000000.txt"
    path.write_text(GT_LINE + "\n" + "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n")
    labels = read_label_file(str(path))
    assert labels.types == ["Car", "DontCare"] and labels.scores is None
    np.testing.assert_allclose(labels.boxes_cam[0], [-0.65, 0.885, 46.70, 3.64, 1.65, 1.67, -1.59])
    np.testing.assert_allclose(labels.bbox2d[0], [587.01, 173.33, 614.12, 200.12])
    assert len(labels.select("Car")) == 1 and len(labels.select("Pedestrian")) == 0


def test_round_trip_with_scores(tmp_path):
    rng = np.random.default_rng(0)
    boxes = np.concatenate([rng.normal(size=(5, 3)), rng.uniform(0.5, 4, (5, 3)), rng.uniform(-3, 3, (5, 1))], 1)
    labels = FrameLabels(types=["Car", "Car", "Pedestrian", "Cyclist", "Car"], boxes_cam=boxes,
                         scores=rng.uniform(size=5), occluded=np.array([0, 1, 2, 3, 0]))
    write_label_file(str(tmp_path / "000007.txt"), labels)
    write_label_file(str(tmp_path / "000008.txt"), FrameLabels(types=[], boxes_cam=np.zeros((0, 7)), scores=np.zeros(0)))
    back = read_label_dir(str(tmp_path), require_score=True)
    assert sorted(back) == ["000007", "000008"] and len(back["000008"]) == 0
    got = back["000007"]
    assert got.types == labels.types
    np.testing.assert_allclose(got.boxes_cam, boxes, rtol=0, atol=1e-12)  # y: ± h/2 rounds once each way
    np.testing.assert_array_equal(got.scores, labels.scores)
    np.testing.assert_array_equal(got.occluded, labels.occluded)


@pytest.mark.parametrize("line, why", [
    ("Car 0 0 0 1 2 3\n", "fields"),
    (GT_LINE.replace("1.65", "abc"), "abc"),
    (GT_LINE.replace("1.65", "nan"), "non-finite"),
    (GT_LINE.replace("1.65", "-1.65"), "negative"),
])
def test_malformed_line_names_file_and_line(tmp_path, line, why):
    path = tmp_path / "000003.txt"
    path.write_text(GT_LINE + line)
    with pytest.raises(DataError, match=rf"000003\.txt:2: .*{why}"):
        read_label_file(str(path))


def test_prediction_without_score_is_an_error(tmp_path):
    path = tmp_path / "000001.txt"
    path.write_text(GT_LINE)
    with pytest.raises(DataError, match=r"000001\.txt:1: .*16 fields"):
        read_label_file(str(path), require_score=True)
    with pytest.raises(DataError, match="label directory not found"):
        read_label_dir(str(tmp_path / "missing"))
