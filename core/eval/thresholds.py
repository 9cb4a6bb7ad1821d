"""IoU thresholds of the box evaluations and their JSON keys.

Every box evaluation (KITTI label files, the bundle's detector, moving objects) reports AP per IoU
threshold under the key `threshold_key(t)` ("0.5", "0.33"), so reports and the benchmark read one
spelling of a threshold.
"""

from __future__ import annotations

from core.errors import DataError

DEFAULT_IOUS = (0.33, 0.5, 0.75)


def threshold_key(t: float) -> str:
    """JSON key of an IoU threshold: 0.5 -> "0.5", 0.33 -> "0.33"."""
    return format(float(t), "g")


def iou_thresholds(extra=()) -> tuple[float, ...]:
    """DEFAULT_IOUS plus `extra`, sorted and deduplicated; DataError for any outside (0, 1]."""
    out = sorted({round(float(t), 6) for t in (*DEFAULT_IOUS, *(extra or ()))})
    bad = [t for t in out if not 0.0 < t <= 1.0]
    if bad:
        raise DataError(f"IoU thresholds must be in (0, 1], got {bad}")
    return tuple(out)


def none_if_nan(x: float) -> float | None:
    """An AP for JSON: None where it is undefined (NaN: no ground-truth box), else a float."""
    return None if x != x else float(x)
