"""The record schema: every kind of violation is a one-line DataError naming the place and the key."""

from __future__ import annotations

import numpy as np
import pytest

from core.data.record import RECORD_KEYS, empty_boxes, record_dims, validate_record
from core.errors import DataError

WHERE = "shard-00003.tar record ep000042"


def test_valid_record_passes_and_reports_dims(make_record):
    rec = make_record(T=3, V=2, H=5, W=7, K=4)
    assert validate_record(rec, WHERE) == {"T": 3, "V": 2, "H": 5, "W": 7, "K": 4}
    assert record_dims(rec) == {"T": 3, "V": 2, "H": 5, "W": 7, "K": 4}


def test_zero_boxes_are_valid(make_record):
    rec = make_record(T=2, K=0)
    rec.update(empty_boxes(2))
    assert validate_record(rec, WHERE)["K"] == 0


def _expect(rec, *fragments):
    with pytest.raises(DataError) as err:
        validate_record(rec, WHERE)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(WHERE + ":")
    for f in fragments:
        assert f in msg, msg


@pytest.mark.parametrize("key", RECORD_KEYS)
def test_missing_key(make_record, key):
    rec = make_record()
    del rec[key]
    _expect(rec, f"'{key}'", "missing")


def test_extra_key(make_record):
    rec = make_record()
    rec["labels"] = np.zeros(3)
    _expect(rec, "'labels'", "not part of the record schema")


@pytest.mark.parametrize("key,bad", [("rgb", np.float32), ("depth", np.float64), ("box_id", np.int64),
                                     ("box_valid", np.uint8), ("world_T_cam", np.float64)])
def test_wrong_dtype(make_record, key, bad):
    rec = make_record()
    rec[key] = rec[key].astype(bad)
    _expect(rec, f"'{key}'", "dtype", np.dtype(bad).name)


def test_not_an_array(make_record):
    rec = make_record()
    rec["box_id"] = [1, 2, 3]
    _expect(rec, "'box_id'", "numpy array")


def test_wrong_rank_and_fixed_dim(make_record):
    rec = make_record()
    rec["depth"] = rec["depth"][0]
    _expect(rec, "'depth'", "expected shape T×V×H×W")
    rec = make_record()
    rec["boxes"] = np.zeros((2, 3, 6), np.float32)
    _expect(rec, "'boxes'", "T×K×7", "2×3×6")


@pytest.mark.parametrize("key,shape,dim", [
    ("depth", (2, 2, 4, 5), "W"),          # W disagrees with rgb
    ("pix_T_cam", (3, 4, 4), "V"),         # V disagrees
    ("world_T_ref", (1, 4, 4), "T"),       # T disagrees
    ("box_moving", (2,), "K"),             # K disagrees with boxes
])
def test_cross_key_disagreement(make_record, key, shape, dim):
    rec = make_record(T=2, V=2, H=4, W=6, K=3)
    rec[key] = np.zeros(shape, rec[key].dtype)
    _expect(rec, f"'{key}'", f"dim {dim}=")


@pytest.mark.parametrize("key", ["world_T_cam", "world_T_ref"])
def test_non_finite_pose(make_record, key):
    rec = make_record()
    rec[key][0, ..., 0, 3] = np.nan
    _expect(rec, f"'{key}'", "non-finite pose")


def test_bad_values(make_record):
    rec = make_record()
    rec["depth"][0, 0, 0, 0] = -1.0
    _expect(rec, "'depth'", "negative")
    rec = make_record()
    rec["boxes"][0, 0, 0] = np.inf
    _expect(rec, "'boxes'", "non-finite")
    rec = make_record()
    rec["pix_T_cam"][1, 0, 0] = 0.0
    _expect(rec, "'pix_T_cam'", "focal")
    rec = make_record()
    rec["world_T_ref"][0, 3, 0] = 1.0
    _expect(rec, "'world_T_ref'", "bottom row")
    rec = make_record()
    rec["pix_T_cam"][0, 0, 1] = 0.5                     # skew
    _expect(rec, "'pix_T_cam'", "pinhole")
    rec = make_record()
    rec["world_T_cam"][0, 0, 0, 0] = 1.1                # a scaled axis: not a rotation
    _expect(rec, "'world_T_cam'", "rigid")
    rec = make_record()
    rec["world_T_ref"][0, :3, :3] = np.diag([1.0, 1.0, -1.0])   # a reflection: orthogonal, det −1
    _expect(rec, "'world_T_ref'", "rigid")
    rec = make_record()                                  # float32 round-off of a real rotation passes
    c, s_ = np.cos(0.3), np.sin(0.3)
    rec["world_T_cam"][0, 0, :3, :3] = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]], np.float32)
    validate_record(rec, "x")


def test_empty_time_axis(make_record):
    rec = make_record(T=0)
    _expect(rec, "dim T must be at least 1")
