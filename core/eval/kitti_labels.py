"""KITTI-format label files: one `<frame>.txt` per frame, one object per line.

Each line: `type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry [score]` with (x, y, z) the
BOTTOM centre of the box in rectified camera coordinates (X right, Y down, Z forward, metres),
(h, w, l) its height, width, length and `ry` its rotation about Y. Predictions carry the trailing
score column; ground truth does not. `DontCare` rows are read like any other type (the evaluator
picks classes by name, so they are ignored unless asked for).

In memory boxes use the canonical encoding of docs/conventions.md#boxes in the `cam` frame: rows
(x, y, z, lx, ly, lz, yaw) with the box CENTRE, lx = l, ly = h, lz = w, yaw = ry; the centre sits
h/2 above the bottom, i.e. y_centre = y_bottom − h/2 because Y points down. The conversion is
core.geometry.boxes.kitti_to_boxes / boxes_to_kitti.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import torch

from core.errors import DataError
from core.geometry.boxes import boxes_to_kitti, kitti_to_boxes

_GT_FIELDS = 15
_PRED_FIELDS = 16


@dataclass
class FrameLabels:
    """The objects of one frame. boxes_cam: N×7 canonical, float64; scores: N or None."""

    types: list[str]
    boxes_cam: np.ndarray
    scores: np.ndarray | None = None
    truncated: np.ndarray = field(default=None)  # N float
    occluded: np.ndarray = field(default=None)   # N int
    alpha: np.ndarray = field(default=None)      # N float
    bbox2d: np.ndarray = field(default=None)     # N×4 (x1, y1, x2, y2) pixels

    def __post_init__(self) -> None:
        n = len(self.types)
        self.boxes_cam = np.asarray(self.boxes_cam, dtype=np.float64).reshape(n, 7)
        if self.scores is not None:
            self.scores = np.asarray(self.scores, dtype=np.float64).reshape(n)
        self.truncated = np.zeros(n) if self.truncated is None else np.asarray(self.truncated, np.float64)
        self.occluded = np.zeros(n, np.int64) if self.occluded is None else np.asarray(self.occluded, np.int64)
        self.alpha = np.full(n, -10.0) if self.alpha is None else np.asarray(self.alpha, np.float64)
        self.bbox2d = np.zeros((n, 4)) if self.bbox2d is None else np.asarray(self.bbox2d, np.float64).reshape(n, 4)

    def __len__(self) -> int:
        return len(self.types)

    def select(self, class_name: str) -> "FrameLabels":
        """The rows whose type is `class_name` (exact match)."""
        keep = np.array([t == class_name for t in self.types], dtype=bool)
        return FrameLabels(types=[t for t in self.types if t == class_name], boxes_cam=self.boxes_cam[keep],
                           scores=None if self.scores is None else self.scores[keep],
                           truncated=self.truncated[keep], occluded=self.occluded[keep],
                           alpha=self.alpha[keep], bbox2d=self.bbox2d[keep])


def _kitti_rows_to_boxes(hwl: np.ndarray, bottom_xyz: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """KITTI (h, w, l) N×3, bottom centre N×3, ry N -> canonical boxes N×7 (float64) in the same frame."""
    rows = np.concatenate([np.reshape(hwl, (-1, 3)), np.reshape(bottom_xyz, (-1, 3)), np.reshape(ry, (-1, 1))], 1)
    return kitti_to_boxes(torch.from_numpy(rows.astype(np.float64))).numpy()  # N×7


def _boxes_to_kitti_rows(boxes_cam: np.ndarray):
    """Canonical boxes N×7 in a camera frame -> (hwl N×3, bottom centre N×3, ry N)."""
    rows = boxes_to_kitti(torch.from_numpy(np.asarray(boxes_cam, np.float64).reshape(-1, 7))).numpy()  # N×7
    return rows[:, 0:3], rows[:, 3:6], rows[:, 6]


def parse_label_line(line: str, *, where: str, require_score: bool):
    """One label line -> (type, truncated, occluded, alpha, bbox2d 4, hwl 3, bottom xyz 3, ry, score|None).

    Raises DataError naming `where` (e.g. "labels/000001.txt:3") when the line is malformed.
    """
    parts = line.split()
    want = f"{_PRED_FIELDS} fields (type trunc occ alpha x1 y1 x2 y2 h w l x y z ry score)" if require_score \
        else f"{_GT_FIELDS} or {_PRED_FIELDS} fields (type trunc occ alpha x1 y1 x2 y2 h w l x y z ry [score])"
    if len(parts) not in (_GT_FIELDS, _PRED_FIELDS) or (require_score and len(parts) != _PRED_FIELDS):
        raise DataError(f"{where}: malformed KITTI label line: expected {want}, got {len(parts)} fields")
    try:
        values = [float(v) for v in parts[1:]]
    except ValueError as e:
        raise DataError(f"{where}: malformed KITTI label line: {e}") from None
    if not all(math.isfinite(v) for v in values):
        raise DataError(f"{where}: malformed KITTI label line: non-finite number")
    trunc, occ, alpha = values[0], values[1], values[2]
    bbox2d, hwl, xyz, ry = values[3:7], values[7:10], values[10:13], values[13]
    if parts[0] != "DontCare" and min(hwl) < 0:
        raise DataError(f"{where}: malformed KITTI label line: negative box size h w l = {hwl}")
    score = values[14] if len(values) == _PRED_FIELDS - 1 else None
    return parts[0], trunc, int(occ), alpha, bbox2d, hwl, xyz, ry, score


def read_label_file(path: str, *, require_score: bool = False) -> FrameLabels:
    """Read one `<frame>.txt`. Blank lines are skipped. Scores are kept only if every row has one."""
    rows = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            if line.strip():
                rows.append(parse_label_line(line, where=f"{path}:{lineno}", require_score=require_score))
    if not rows:
        return FrameLabels(types=[], boxes_cam=np.zeros((0, 7)), scores=np.zeros(0) if require_score else None)
    types, trunc, occ, alpha, bbox2d, hwl, xyz, ry, score = zip(*rows)
    has_score = [s is not None for s in score]
    if any(has_score) and not all(has_score):
        lineno = has_score.index(False) + 1
        raise DataError(f"{path}: some rows have a score column and some do not (first without: row {lineno})")
    return FrameLabels(types=list(types), boxes_cam=_kitti_rows_to_boxes(np.array(hwl), np.array(xyz), np.array(ry)),
                       scores=np.array(score, np.float64) if all(has_score) else None,
                       truncated=np.array(trunc), occluded=np.array(occ), alpha=np.array(alpha),
                       bbox2d=np.array(bbox2d))


def write_label_file(path: str, labels: FrameLabels) -> None:
    """Write one `<frame>.txt` (with the score column when `labels.scores` is set)."""
    hwl, bottom, ry = _boxes_to_kitti_rows(labels.boxes_cam)
    lines = []
    for i, kind in enumerate(labels.types):
        if any(c.isspace() for c in kind) or not kind:
            raise DataError(f"{path}: object type {kind!r} cannot be written (empty or contains spaces)")
        vals = [labels.truncated[i], labels.occluded[i], labels.alpha[i], *labels.bbox2d[i], *hwl[i], *bottom[i], ry[i]]
        text = kind + " " + " ".join(_fmt(v) for v in vals)
        if labels.scores is not None:
            text += " " + _fmt(labels.scores[i])
        lines.append(text)
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + ("\n" if lines else ""))


def _fmt(v) -> str:
    # repr of a float64 round-trips exactly; integers stay integers (the occluded column).
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return repr(float(v))


def list_frames(directory: str) -> list[str]:
    """Frame names (file stems) of the `*.txt` files in `directory`, sorted."""
    if not os.path.isdir(directory):
        raise DataError(f"label directory not found: {directory}")
    return sorted(name[:-4] for name in os.listdir(directory) if name.endswith(".txt"))


def read_label_dir(directory: str, *, require_score: bool = False) -> dict[str, FrameLabels]:
    """Every `<frame>.txt` in `directory` -> {frame: FrameLabels}."""
    return {frame: read_label_file(os.path.join(directory, frame + ".txt"), require_score=require_score)
            for frame in list_frames(directory)}
