"""The record: one training/evaluation example as a dict of numpy arrays (docs/data.md#records).

| key           | dtype   | shape       | meaning                                               |
|---------------|---------|-------------|-------------------------------------------------------|
| `rgb`         | uint8   | T×V×H×W×3   | T time steps × V camera views                         |
| `depth`       | float32 | T×V×H×W     | metres along camera Z; 0 = no return                  |
| `pix_T_cam`   | float32 | V×4×4       | intrinsics per view                                   |
| `world_T_cam` | float32 | T×V×4×4     | camera poses                                          |
| `world_T_ref` | float32 | T×4×4       | the map's reference frame at each step                |
| `boxes`       | float32 | T×K×7       | boxes in `world`, rows (x, y, z, lx, ly, lz, yaw)     |
| `box_valid`   | bool    | T×K         | which rows are real                                   |
| `box_id`      | int32   | K           | track id per row (stable over T)                      |
| `box_moving`  | bool    | K           | the object moves independently in this record        |

Frames and units follow docs/conventions.md (OpenCV cameras, metres, radians, `a_T_b` poses).
A record holds exactly these keys; `validate_record` enforces keys, dtypes, ranks, the agreement of
T, V, H, W, K across keys, and finite values, and raises `DataError` with one line naming the place
(e.g. "shard-00003.tar record ep000042") and the offending key.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from core.errors import DataError

RIGID_TOL = 1e-3   # |RᵀR − I| of a pose's rotation: float32 round-off of a real rotation sits far below it

# key -> (dtype, named dims). Dim names shared between keys must agree within one record.
RECORD_SCHEMA: dict[str, tuple[np.dtype, tuple[str | int, ...]]] = {
    "rgb": (np.dtype(np.uint8), ("T", "V", "H", "W", 3)),
    "depth": (np.dtype(np.float32), ("T", "V", "H", "W")),
    "pix_T_cam": (np.dtype(np.float32), ("V", 4, 4)),
    "world_T_cam": (np.dtype(np.float32), ("T", "V", 4, 4)),
    "world_T_ref": (np.dtype(np.float32), ("T", 4, 4)),
    "boxes": (np.dtype(np.float32), ("T", "K", 7)),
    "box_valid": (np.dtype(np.bool_), ("T", "K")),
    "box_id": (np.dtype(np.int32), ("K",)),
    "box_moving": (np.dtype(np.bool_), ("K",)),
}
RECORD_KEYS: tuple[str, ...] = tuple(RECORD_SCHEMA)

# Float keys that must hold only finite numbers (NaN/inf in a pose or box poisons every loss).
_FINITE_KEYS = ("depth", "pix_T_cam", "world_T_cam", "world_T_ref", "boxes")
_POSE_KEYS = ("world_T_cam", "world_T_ref")


def _dims_text(dims: tuple) -> str:
    return "×".join(str(d) for d in dims)


def validate_record(rec: Mapping[str, np.ndarray], where: str) -> dict[str, int]:
    """Check `rec` against the schema; return its dims {T, V, H, W, K}.

    Raises DataError("<where>: key '<k>': <what is wrong>") on a missing or unexpected key, a
    non-array value, a wrong dtype, rank or dimension, disagreeing dims between keys, a non-finite
    value, a negative depth, an intrinsics matrix that is not a pinhole one with positive focal lengths, or a
    pose whose bottom row is not (0, 0, 0, 1) or whose rotation is not one (|RᵀR − I| ≤ RIGID_TOL, det R > 0) —
    the checks the inference service makes of the same matrices (services/inference/validation.py).
    """
    if not isinstance(rec, Mapping):
        raise DataError(f"{where}: a record must be a dict of arrays, got {type(rec).__name__}")
    missing = [k for k in RECORD_KEYS if k not in rec]
    if missing:
        raise DataError(f"{where}: key '{missing[0]}' is missing"
                        + (f" (also missing: {', '.join(missing[1:])})" if len(missing) > 1 else ""))
    extra = sorted(k for k in rec if k not in RECORD_SCHEMA)
    if extra:
        raise DataError(f"{where}: key '{extra[0]}' is not part of the record schema "
                        f"(expected exactly {', '.join(RECORD_KEYS)})")

    dims: dict[str, int] = {}
    dim_source: dict[str, str] = {}
    for key, (dtype, named) in RECORD_SCHEMA.items():
        value = rec[key]
        if not isinstance(value, np.ndarray):
            raise DataError(f"{where}: key '{key}': expected a numpy array, got {type(value).__name__}")
        if value.dtype != dtype:
            raise DataError(f"{where}: key '{key}': expected dtype {dtype}, got {value.dtype}")
        if value.ndim != len(named):
            raise DataError(f"{where}: key '{key}': expected shape {_dims_text(named)}, "
                            f"got {_dims_text(value.shape) or 'scalar'}")
        for name, size in zip(named, value.shape):
            if isinstance(name, int):
                if size != name:
                    raise DataError(f"{where}: key '{key}': expected shape {_dims_text(named)}, "
                                    f"got {_dims_text(value.shape)}")
            elif name in dims:
                if dims[name] != size:
                    raise DataError(f"{where}: key '{key}': dim {name}={size} disagrees with "
                                    f"{name}={dims[name]} of key '{dim_source[name]}' "
                                    f"(shape {_dims_text(value.shape)})")
            else:
                dims[name] = size
                dim_source[name] = key
    for name in ("T", "V", "H", "W"):
        if dims[name] < 1:
            raise DataError(f"{where}: key '{dim_source[name]}': dim {name} must be at least 1, got 0")

    for key in _FINITE_KEYS:
        if not np.isfinite(rec[key]).all():
            what = "pose" if key in _POSE_KEYS else "value"
            raise DataError(f"{where}: key '{key}': non-finite {what} (NaN or inf)")
    if (rec["depth"] < 0).any():
        raise DataError(f"{where}: key 'depth': negative depth (0 means missing; depth is metres along Z)")
    pix_T_cam = rec["pix_T_cam"]
    if not ((pix_T_cam[:, 0, 0] > 0).all() and (pix_T_cam[:, 1, 1] > 0).all()):
        raise DataError(f"{where}: key 'pix_T_cam': focal lengths fx=[0,0], fy=[1,1] must be positive")
    pinhole = np.array([[0, 1, 0, 0], [1, 0, 0, 0], [1, 1, 1, 1], [1, 1, 1, 1]], bool)   # entries that must be 0/1
    want = np.array([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)
    if (np.abs(pix_T_cam.astype(np.float64) - want)[:, pinhole] > 1e-6).any():
        raise DataError(f"{where}: key 'pix_T_cam': must be pinhole matrices [[fx,0,cx,0],[0,fy,cy,0],[0,0,1,0],"
                        "[0,0,0,1]] (no skew)")
    for key in _POSE_KEYS:
        bottom = rec[key][..., 3, :]
        if not np.allclose(bottom, np.array([0, 0, 0, 1], np.float32), atol=1e-5):
            raise DataError(f"{where}: key '{key}': pose bottom row must be (0, 0, 0, 1)")
        R = rec[key][..., :3, :3].astype(np.float64)                                      # ...×3×3
        orthogonality = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max()
        if orthogonality > RIGID_TOL or (np.linalg.det(R) <= 0).any():
            raise DataError(f"{where}: key '{key}': poses must be rigid (|RᵀR − I| ≤ {RIGID_TOL:g}, det R > 0), got "
                            f"|RᵀR − I| = {orthogonality:.2g}, det R from {np.linalg.det(R).min():.3g}")
    return dims


def record_dims(rec: Mapping[str, np.ndarray]) -> dict[str, int]:
    """{T, V, H, W, K} of a record (no validation; use validate_record for untrusted data)."""
    T, V, H, W, _ = rec["rgb"].shape
    return {"T": int(T), "V": int(V), "H": int(H), "W": int(W), "K": int(rec["box_id"].shape[0])}


def empty_boxes(T: int) -> dict[str, np.ndarray]:
    """The box keys of a record without objects (K = 0): boxes T×0×7, box_valid T×0, box_id 0, box_moving 0."""
    return {
        "boxes": np.zeros((T, 0, 7), np.float32),
        "box_valid": np.zeros((T, 0), np.bool_),
        "box_id": np.zeros((0,), np.int32),
        "box_moving": np.zeros((0,), np.bool_),
    }
