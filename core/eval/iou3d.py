"""Exact IoU of yaw-rotated 3D boxes and of their bird's-eye-view footprints, on CPU.

Conventions (docs/conventions.md#boxes): boxes are rows `(x, y, z, lx, ly, lz, yaw)` — centre in a named
camera-like frame (X right, Y down, Z forward), lengths along the object's own axes (lx = length,
ly = height, lz = width), `yaw` about the frame's Y axis with R = [[c,0,s],[0,1,0],[-s,0,c]].
Both box sets passed to one function must be in the same frame.

The bird's-eye view is the (x, z) plane: a box's footprint is the rectangle spanned by the object's
x axis (c, -s) × lx and z axis (s, c) × lz around (x, z); its height is the interval y ± ly/2.
The footprint intersection is found by Sutherland–Hodgman clipping of one rectangle by the other
(exact for convex polygons), vectorised over all candidate pairs; 3D IoU = footprint overlap ×
height overlap / union of volumes. Everything runs in float64 numpy.
"""

from __future__ import annotations

import numpy as np

from core.errors import ShapeError

# Pairs clipped per vectorised step: bounds the temporaries (about 1 KB per pair) to ~64 MB.
_PAIRS_PER_CHUNK = 65536
# Clipping a convex polygon by one half-plane adds at most one vertex; each step keeps room for
# two, so the truncation in `_clip_by_halfplane` stays harmless should rounding make a
# near-degenerate step emit one more than the exact count.
_SPARE_PER_STEP = 2


def as_boxes(boxes, name: str = "boxes") -> np.ndarray:
    """Any array-like (numpy, torch CPU/GPU, list) of boxes as a float64 N×7 array."""
    if hasattr(boxes, "detach"):
        boxes = boxes.detach().cpu().numpy()
    arr = np.asarray(boxes, dtype=np.float64)
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 7)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ShapeError(f"{name}: expected shape N×7 (x,y,z,lx,ly,lz,yaw), got {'×'.join(map(str, arr.shape))}")
    return arr


def bev_corners(boxes) -> np.ndarray:
    """Footprint corners in the (x, z) plane, counter-clockwise (positive signed area).

    boxes: N×7 canonical boxes. Returns N×4×2 with columns (x, z).
    """
    b = as_boxes(boxes)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    axis_len = np.stack([c, -s], axis=-1) * (b[:, 3:4] / 2)  # N×2: object x axis in (x, z), half length
    axis_wid = np.stack([s, c], axis=-1) * (b[:, 5:6] / 2)   # N×2: object z axis in (x, z), half width
    centre = b[:, [0, 2]]                                     # N×2
    # (+,+), (-,+), (-,-), (+,-) in object coordinates is counter-clockwise there, and the map
    # object -> (x, z) has determinant c² + s² = 1 > 0, so the order stays counter-clockwise.
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)  # 4×2
    return (centre[:, None, :] + signs[None, :, 0:1] * axis_len[:, None, :]
            + signs[None, :, 1:2] * axis_wid[:, None, :])  # N×4×2


def _polygon_area(vertices: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Shoelace area of P padded polygons: vertices P×V×2, count P valid vertices each."""
    P, V, _ = vertices.shape
    idx = np.arange(V)[None, :]                                    # 1×V
    nxt = np.where(idx + 1 < count[:, None], idx + 1, 0)           # P×V: cyclic successor
    valid = idx < count[:, None]                                   # P×V
    x, z = vertices[..., 0], vertices[..., 1]
    xn = np.take_along_axis(x, nxt, axis=1)
    zn = np.take_along_axis(z, nxt, axis=1)
    cross = np.where(valid, x * zn - xn * z, 0.0)
    return 0.5 * np.abs(cross.sum(axis=1))


def _clip_by_halfplane(poly: np.ndarray, count: np.ndarray, a: np.ndarray, b: np.ndarray, out_vertices: int):
    """One Sutherland–Hodgman step: keep the part of each polygon left of the directed edge a→b.

    poly: P×V×2 padded polygons with `count` valid vertices; a, b: P×2 edge endpoints of a
    counter-clockwise clip polygon (its interior is on the left). Returns (P×V'×2, P) with the
    result truncated to V' = out_vertices, which is exact when V' bounds the true vertex count.
    """
    P, V, _ = poly.shape
    edge = b - a                                                           # P×2
    rel = poly - a[:, None, :]                                             # P×V×2
    side = edge[:, None, 0] * rel[..., 1] - edge[:, None, 1] * rel[..., 0]  # P×V, ≥ 0 inside
    idx = np.arange(V)[None, :]
    valid = idx < count[:, None]                                           # P×V
    nxt = np.where(idx + 1 < count[:, None], idx + 1, 0)                   # P×V
    side_n = np.take_along_axis(side, nxt, axis=1)
    poly_n = np.take_along_axis(poly, nxt[..., None].repeat(2, axis=2), axis=1)  # P×V×2
    inside, inside_n = side >= 0, side_n >= 0
    # Where the edge cur→next crosses the clip line, emit the crossing point after `cur`.
    crosses = valid & (inside != inside_n)
    denom = np.where(crosses, side - side_n, 1.0)  # nonzero whenever the signs differ
    t = np.where(crosses, side / denom, 0.0)
    crossing = poly + t[..., None] * (poly_n - poly)                       # P×V×2
    cand = np.stack([poly, crossing], axis=2).reshape(P, 2 * V, 2)         # P×2V×2: cur, crossing
    keep = np.stack([valid & inside, crosses], axis=2).reshape(P, 2 * V)   # P×2V
    # Compact the kept vertices to the front, preserving their order: each kept vertex goes to
    # slot (number kept before it); dropped ones and any overflow go to one extra slot, cut off after.
    slot = np.cumsum(keep, axis=1) - 1                                     # P×2V
    slot = np.where(keep & (slot < out_vertices), slot, out_vertices)
    out = np.zeros((P, out_vertices + 1, 2))
    out[np.arange(P)[:, None], slot] = cand
    new_count = np.minimum(keep.sum(axis=1), out_vertices)
    return out[:, :out_vertices], new_count


def _intersection_area_pairs(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """Area of rectangle ca[p] ∩ rectangle cb[p] for P pairs: ca, cb P×4×2 counter-clockwise."""
    poly = ca
    count = np.full(ca.shape[0], 4)
    for k in range(4):
        poly, count = _clip_by_halfplane(poly, count, cb[:, k], cb[:, (k + 1) % 4],
                                         poly.shape[1] + _SPARE_PER_STEP)
    return _polygon_area(poly, count)


def bev_intersection_area(boxes_a, boxes_b) -> np.ndarray:
    """Pairwise footprint intersection areas (m²): boxes_a N×7, boxes_b M×7 -> N×M float64."""
    a, b = as_boxes(boxes_a, "boxes_a"), as_boxes(boxes_b, "boxes_b")
    N, M = len(a), len(b)
    out = np.zeros((N, M))
    if N == 0 or M == 0:
        return out
    ca, cb = bev_corners(a), bev_corners(b)  # N×4×2, M×4×2
    # Only pairs whose circumscribed circles meet can overlap; skip the rest (most pairs in a scene).
    ra = 0.5 * np.hypot(a[:, 3], a[:, 5])
    rb = 0.5 * np.hypot(b[:, 3], b[:, 5])
    dist = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 2] - b[None, :, 2])  # N×M
    ia, ib = np.nonzero(dist <= ra[:, None] + rb[None, :])
    for start in range(0, len(ia), _PAIRS_PER_CHUNK):
        sa, sb = ia[start:start + _PAIRS_PER_CHUNK], ib[start:start + _PAIRS_PER_CHUNK]
        out[sa, sb] = _intersection_area_pairs(ca[sa], cb[sb])
    return out


def height_overlap(boxes_a, boxes_b) -> np.ndarray:
    """Pairwise overlap (m) of the vertical intervals y ± ly/2: N×7, M×7 -> N×M."""
    a, b = as_boxes(boxes_a, "boxes_a"), as_boxes(boxes_b, "boxes_b")
    top = np.maximum(a[:, None, 1] - a[:, None, 4] / 2, b[None, :, 1] - b[None, :, 4] / 2)
    bottom = np.minimum(a[:, None, 1] + a[:, None, 4] / 2, b[None, :, 1] + b[None, :, 4] / 2)
    return np.clip(bottom - top, 0.0, None)


def _safe_ratio(inter: np.ndarray, union: np.ndarray) -> np.ndarray:
    # Degenerate (zero-size) boxes have union 0: their IoU is 0, not NaN.
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def iou_bev(boxes_a, boxes_b) -> np.ndarray:
    """Pairwise bird's-eye-view IoU of the (x, z) footprints: N×7, M×7 -> N×M in [0, 1]."""
    a, b = as_boxes(boxes_a, "boxes_a"), as_boxes(boxes_b, "boxes_b")
    inter = bev_intersection_area(a, b)
    area_a, area_b = a[:, 3] * a[:, 5], b[:, 3] * b[:, 5]
    return _safe_ratio(inter, area_a[:, None] + area_b[None, :] - inter)


def iou_3d(boxes_a, boxes_b) -> np.ndarray:
    """Pairwise exact 3D IoU of yaw-rotated boxes: N×7, M×7 -> N×M in [0, 1]."""
    a, b = as_boxes(boxes_a, "boxes_a"), as_boxes(boxes_b, "boxes_b")
    inter = bev_intersection_area(a, b) * height_overlap(a, b)
    vol_a, vol_b = a[:, 3] * a[:, 4] * a[:, 5], b[:, 3] * b[:, 4] * b[:, 5]
    return _safe_ratio(inter, vol_a[:, None] + vol_b[None, :] - inter)


def iou_3d_across_frames(boxes_a, boxes_b, a_T_b, *, samples_per_side: int = 16) -> np.ndarray:
    """Pairwise 3D IoU of boxes given in two frames related by any rigid a_T_b (4×4): N×7 in frame a,
    M×7 in frame b -> N×M in [0, 1].

    When a_T_b is not a rotation about Y, a box of frame b is no canonical box of frame a (a tilted
    camera frame against a gravity-aligned one), so the exact clipping of `iou_3d` does not apply. The
    intersection is measured instead by a midpoint lattice of samples_per_side³ points in each box of a:
    |A ∩ B| ≈ vol(A) · (share of A's lattice inside B). Error: about one lattice cell's slab, a few per cent
    at 16 per side (checked against `iou_3d` where both apply)."""
    a, b = as_boxes(boxes_a, "boxes_a"), as_boxes(boxes_b, "boxes_b")
    T = np.asarray(a_T_b, dtype=np.float64).reshape(4, 4)
    out = np.zeros((len(a), len(b)))
    if len(a) == 0 or len(b) == 0:
        return out
    n = samples_per_side
    u = (np.arange(n) + 0.5) / n - 0.5                                   # n cell midpoints in [−½, ½]
    unit = np.stack(np.meshgrid(u, u, u, indexing="ij"), axis=-1).reshape(-1, 3)   # n³×3
    b_T_a = np.linalg.inv(T)
    vol_a, vol_b = a[:, 3] * a[:, 4] * a[:, 5], b[:, 3] * b[:, 4] * b[:, 5]
    for i, box in enumerate(a):
        pts_a = (unit * box[3:6]) @ _yaw_matrix(box[6]).T + box[:3]       # n³×3 in frame a
        pts_b = pts_a @ b_T_a[:3, :3].T + b_T_a[:3, 3]                     # n³×3 in frame b
        for j, other in enumerate(b):
            local = (pts_b - other[:3]) @ _yaw_matrix(other[6])           # n³×3 in box j's own axes
            inside = np.all(np.abs(local) <= other[3:6] / 2, axis=1).mean()
            inter = inside * vol_a[i]
            out[i, j] = inter / (vol_a[i] + vol_b[j] - inter) if inter > 0 else 0.0
    return out


def _yaw_matrix(yaw: float) -> np.ndarray:
    """Object -> frame rotation of a canonical box (about Y)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
