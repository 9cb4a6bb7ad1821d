"""Validation of decoded request arrays: shapes, dtypes, finite values, rigid poses, intrinsics.

Every check raises InvalidInput naming the offending field (e.g. `views[1].pix_T_cam`), so a
client's mistake is always a 4xx, never a 500. Transports decode bytes (codecs.py) and hand the
arrays to `make_view` / `stack_views`; the runtime only ever sees validated `Views`.
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field

import numpy as np

from services.inference.errors import InvalidInput

MAX_VIEWS = 16
MAX_SIDE = 4096
RIGID_TOL = 1e-3
MAX_DEPTH_M = 1000.0
FLOAT32_MAX = float(np.finfo(np.float32).max)
# Views fused as one instant must have been captured together: a car at 10 m/s moves 0.5 m in 50 ms, about a
# voxel at the presets' resolutions, so views further apart than this would fuse it twice.
MAX_VIEW_SKEW_S = 0.05
# The shortest interval a pair may span: velocities are displacement / interval, and an interval of 1e-300 s (two
# timestamps a rounding apart) made them inf, which JSON writes as null. 0.1 ms is a 10 kHz camera.
MIN_PAIR_INTERVAL_S = 1e-4
# The smallest focal length, in pixels, after the cast to float32 the model runs in (fx = 1e-46 became 0.0 there
# and 1e-40 a denormal, after the check in float64 had passed them: unprojection then divided by ~0).
MIN_FOCAL_PX = 1e-3


@dataclass(frozen=True)
class View:
    """One validated RGB-D view: rgb H×W×3 uint8, depth H×W float32 metres, 4×4 float32 matrices.
    `posed`: the client gave world_T_cam (else it is the identity, which only a lone view may leave out)."""

    rgb: np.ndarray
    depth: np.ndarray
    pix_T_cam: np.ndarray
    world_T_cam: np.ndarray
    camera_id: str = ""
    sequence: int = 0
    timestamp: float = 0.0
    posed: bool = True
    scene_start: bool = False  # the source cut to a new scene: not paired with the camera's previous frame
    capture_time: float = 0.0  # seconds on the capture clock (0: not given; then `timestamp` times motion)


@dataclass(frozen=True)
class Views:
    """Views of one instant, stacked: rgb V×H×W×3 uint8, depth V×H×W float32, pix_T_cam and
    world_T_cam V×4×4 float32. `ref` is the camera of view 0. `posed`: every view came with its
    world_T_cam (always so for more than one view)."""

    rgb: np.ndarray
    depth: np.ndarray
    pix_T_cam: np.ndarray
    world_T_cam: np.ndarray
    camera_ids: list[str] = dc_field(default_factory=list)
    sequence: int = 0
    timestamp: float = 0.0
    posed: bool = True
    capture_time: float = 0.0

    @property
    def shape_key(self) -> tuple[int, int, int]:
        """(V, H, W): requests batch together only when these agree."""
        V, H, W = self.depth.shape
        return (V, H, W)


def check_rgb(arr: np.ndarray, field: str) -> np.ndarray:
    """H×W×3 uint8 (an H×W×4 array drops its alpha)."""
    if arr.dtype != np.uint8:
        raise InvalidInput(field, f"rgb must be uint8, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 4:
        arr = arr[:, :, :3]
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InvalidInput(field, f"rgb must have shape H×W×3, got {list(arr.shape)}")
    _check_side(arr.shape[0], arr.shape[1], field)
    return np.ascontiguousarray(arr)


def check_depth(arr: np.ndarray, field: str) -> np.ndarray:
    """H×W metres as float32; uint16 arrays are millimetres. Finite, ≥ 0 (0 = missing)."""
    if arr.dtype == np.uint16:
        arr = arr.astype(np.float32) / 1000.0
    elif arr.dtype in (np.float32, np.float64):
        arr = arr.astype(np.float32, copy=False)
    else:
        raise InvalidInput(field, f"depth must be float32 metres or uint16 millimetres, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2:
        raise InvalidInput(field, f"depth must have shape H×W, got {list(arr.shape)}")
    _check_side(arr.shape[0], arr.shape[1], field)
    if not np.isfinite(arr).all():
        raise InvalidInput(field, f"depth has {int((~np.isfinite(arr)).sum())} non-finite values")
    if (arr < 0).any() or (arr > MAX_DEPTH_M).any():
        raise InvalidInput(field, f"depth must lie in [0, {MAX_DEPTH_M:g}] metres (0 = missing)")
    return np.ascontiguousarray(arr)


def _check_matrix(arr: np.ndarray, field: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype.kind not in "fiu":
        raise InvalidInput(field, f"must be a numeric 4×4 matrix, got dtype {arr.dtype}")
    if arr.shape == (16,):
        arr = arr.reshape(4, 4)  # 16 -> 4×4, row-major
    if arr.shape != (4, 4):
        raise InvalidInput(field, f"must have shape 4×4, got {list(arr.shape)}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise InvalidInput(field, "has non-finite entries")
    if np.abs(arr).max() > FLOAT32_MAX:  # the model takes float32: such an entry would turn into inf there
        raise InvalidInput(field, f"has entries beyond float32's range (|x| ≤ {FLOAT32_MAX:.3g})")
    if np.abs(arr[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise InvalidInput(field, f"last row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    return arr


def check_intrinsics(arr, field: str) -> np.ndarray:
    """4×4 pinhole intrinsics with fx, fy > 0, no skew, third row [0, 0, 1, 0]."""
    m = _check_matrix(arr, field)
    fx, fy = np.float32(m[0, 0]), np.float32(m[1, 1])   # as the model will see them
    if not (fx >= MIN_FOCAL_PX and fy >= MIN_FOCAL_PX):
        raise InvalidInput(field, f"focal lengths must be positive, at least {MIN_FOCAL_PX:g} px, got fx={m[0, 0]:g} "
                                  f"fy={m[1, 1]:g}")
    if abs(m[0, 1]) > 1e-6 or abs(m[1, 0]) > 1e-6 or np.abs(m[2] - [0, 0, 1, 0]).max() > 1e-6:
        raise InvalidInput(field, "must be a pinhole matrix [[fx,0,cx,0],[0,fy,cy,0],[0,0,1,0],[0,0,0,1]]")
    return m.astype(np.float32)


def check_pose(arr, field: str) -> np.ndarray:
    """4×4 rigid transform: orthonormal rotation with determinant +1."""
    m = _check_matrix(arr, field)
    R = m[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > RIGID_TOL or np.linalg.det(R) <= 0:
        raise InvalidInput(field, f"is not a rigid transform (|RᵀR − I| = {err:.2g}, "
                                  f"det R = {np.linalg.det(R):.3g})")
    return m.astype(np.float32)


def _check_side(H: int, W: int, field: str) -> None:
    if not (1 <= H <= MAX_SIDE and 1 <= W <= MAX_SIDE):
        raise InvalidInput(field, f"image size {H}×{W} outside 1..{MAX_SIDE}")


def make_view(*, rgb: np.ndarray, depth: np.ndarray, pix_T_cam, world_T_cam=None, field: str,
              camera_id: str = "", sequence: int = 0, timestamp: float = 0.0, scene_start: bool = False,
              capture_time: float = 0.0) -> View:
    """Validate one view's arrays; `field` prefixes the names in errors (e.g. `views[0]`)."""
    rgb = check_rgb(rgb, f"{field}.rgb")
    depth = check_depth(depth, f"{field}.depth")
    if rgb.shape[:2] != depth.shape:
        raise InvalidInput(f"{field}.depth", f"size {depth.shape[0]}×{depth.shape[1]} differs from rgb "
                                             f"{rgb.shape[0]}×{rgb.shape[1]}")
    pix_T_cam = check_intrinsics(pix_T_cam, f"{field}.pix_T_cam")
    posed = world_T_cam is not None
    world_T_cam = check_pose(world_T_cam, f"{field}.world_T_cam") if posed else np.eye(4, dtype=np.float32)
    if not np.isfinite(timestamp):
        raise InvalidInput(f"{field}.timestamp", "must be finite")
    if not (np.isfinite(capture_time) and capture_time >= 0):
        raise InvalidInput(f"{field}.capture_time", f"must be finite seconds >= 0 (0: not given), got {capture_time!r}")
    return View(rgb=rgb, depth=depth, pix_T_cam=pix_T_cam, world_T_cam=world_T_cam,
                camera_id=camera_id, sequence=int(sequence), timestamp=float(timestamp), posed=posed,
                scene_start=bool(scene_start), capture_time=float(capture_time))


def check_view_count(count: int, field: str) -> None:
    """InvalidInput unless 1..MAX_VIEWS views were sent; checked before any view is decoded or validated, because
    that work runs on the server's event loop: a 2 kB .npz of 20 000 one-pixel views took ~1 s of it per
    10 000 views, and the cap allows millions."""
    if not 1 <= count <= MAX_VIEWS:
        raise InvalidInput(field, f"need 1..{MAX_VIEWS} views, got {count}")


def stack_views(views: list[View], field: str) -> Views:
    """Views of one instant -> Views (all the same size, 1..MAX_VIEWS of them; with more than one, each
    with its world_T_cam: fusing views needs where each camera stood, and the identity would be a guess)."""
    check_view_count(len(views), field)
    size = views[0].depth.shape
    for i, v in enumerate(views):
        if v.depth.shape != size:
            raise InvalidInput(f"{field}[{i}]", f"size {v.depth.shape} differs from view 0's {size}")
        if len(views) > 1 and not v.posed:
            raise InvalidInput(f"{field}[{i}].world_T_cam", f"missing: each of the {len(views)} views of one "
                                                            "instant needs its camera pose to be fused with the others")
    captured = [v.capture_time > 0.0 for v in views]
    if any(captured):
        if not all(captured):
            i = captured.index(False)
            raise InvalidInput(f"{field}[{i}].capture_time", f"missing while view {captured.index(True)} of the same "
                                                             "instant has one: give it for every view or for none")
        first = min(range(len(views)), key=lambda i: views[i].capture_time)
        last = max(range(len(views)), key=lambda i: views[i].capture_time)
        skew = views[last].capture_time - views[first].capture_time
        if skew > MAX_VIEW_SKEW_S:
            raise InvalidInput(f"{field}[{last}].capture_time", f"{skew:.3f} s after view {first}'s: views fused as "
                                                                f"one instant must be captured within {MAX_VIEW_SKEW_S} s")
    return Views(rgb=np.stack([v.rgb for v in views]),              # V×H×W×3
                 depth=np.stack([v.depth for v in views]),          # V×H×W
                 pix_T_cam=np.stack([v.pix_T_cam for v in views]),  # V×4×4
                 world_T_cam=np.stack([v.world_T_cam for v in views]),
                 camera_ids=[v.camera_id for v in views], sequence=views[0].sequence,
                 timestamp=max(v.timestamp for v in views), posed=all(v.posed for v in views),
                 capture_time=max(v.capture_time for v in views))


def check_pair(views0: Views, views1: Views, field1: str) -> None:
    """Both instants of a pair request must have the same views layout."""
    if views0.shape_key != views1.shape_key:
        raise InvalidInput(field1, f"views (V, H, W) = {views1.shape_key} differ from the first "
                                   f"instant's {views0.shape_key}")


def pair_interval(views0: Views, views1: Views, *, frame_dt: float, field1: str) -> float:
    """Seconds from the first instant of a pair to the second: the difference of their capture times when
    both carry one (a recording replayed at another rate than it was captured at moves in capture time);
    else of their timestamps; when neither carries one (both 0, the wire's default), the difference of
    their sequence numbers (at least 1) times `frame_dt`. A clock that does not advance is refused, naming
    `field1`.capture_time or `field1`.timestamp."""
    c0, c1 = views0.capture_time, views1.capture_time
    if c0 > 0.0 and c1 > 0.0:
        if not c1 > c0:
            raise InvalidInput(f"{field1}.capture_time", f"{c1!r} s is not after the first instant's {c0!r} s: "
                                                         "the capture clock must advance")
        return _long_enough(c1 - c0, f"{field1}.capture_time")
    t0, t1 = views0.timestamp, views1.timestamp
    if t0 == 0.0 and t1 == 0.0:
        # frame_dt is at least MIN_PAIR_INTERVAL_S (its flag's type), so this needs no _long_enough
        return max(1, views1.sequence - views0.sequence) * frame_dt
    if not t1 > t0:
        raise InvalidInput(f"{field1}.timestamp", f"{t1!r} s is not after the first instant's {t0!r} s: the "
                                                  "frames' clock must advance (or leave both timestamps 0)")
    return _long_enough(t1 - t0, f"{field1}.timestamp")


def _long_enough(interval: float, field: str) -> float:
    if not interval >= MIN_PAIR_INTERVAL_S:
        raise InvalidInput(field, f"the pair spans {interval:g} s, under {MIN_PAIR_INTERVAL_S:g} s: too short to time "
                                  "motion over (velocities would overflow)")
    return interval


def require_poses(views: Views, field: str, why: str) -> None:
    """Refuse, naming `field` (a world_T_cam), views whose poses were not given when `why` needs them."""
    if not views.posed:
        raise InvalidInput(field, f"missing: {why}")


def check_min_score(value: float, field: str = "min_score", *, low: float = 0.0) -> float:
    """A score threshold in [low, 1] (detection objectness: [0, 1]; moving-object saliency: [−1, 1])."""
    if not (np.isfinite(value) and low <= value <= 1.0):
        raise InvalidInput(field, f"must lie in [{low:g}, 1], got {value}")
    return float(value)
