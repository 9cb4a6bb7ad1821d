"""Importer for TUM RGB-D sequences (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).

A sequence directory holds
    rgb.txt, depth.txt   lines `timestamp filename` ('#' comments), 640×480 PNGs
    groundtruth.txt      lines `timestamp tx ty tz qx qy qz qw`: the colour camera's optical centre
                         and orientation in the motion-capture world, i.e. world_T_cam
Depth PNGs are uint16 holding metres × 5000 (0 = missing) and registered to the colour camera.

Each rgb frame is paired one to one with a depth frame within `max_dt` seconds, closest pairs first (as TUM's
own associate.py: a depth frame is never used twice), and with the nearest pose within `max_dt`; frames
without both are skipped and counted. Every `frame_step`-th associated frame is kept, and records are windows
of T consecutive kept frames starting every `stride` frames (default T); a window spanning a gap (a step more
than MAX_GAP_FACTOR × the median step between kept frames: dropped frames, a motion-capture outage) is
skipped and counted, since a record carries no timestamps to show it. V = 1, K = 0. The camera: `intrinsics`,
else TUM_DEPTH_CAMERA for every sequence.
Frames: `world` = the motion-capture world of groundtruth.txt; `ref` = the record's first camera, so
world_T_ref[t] = world_T_cam[0, 0] for every t.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterator, Mapping

import numpy as np
import torch

from core.data.importers._common import read_depth_png, read_rgb, record_key, require_file, write_imported
from core.data.record import empty_boxes
from core.data.shards import DEFAULT_SHARD_BYTES
from core.errors import DataError
from core.geometry import se3

# The camera of every TUM sequence's depth images, (fx, fy, cx, cy) — not the per-sensor colour calibrations
# (freiburg1: 517.3, 516.5, 318.6, 255.3 with lens distortion; ...). The dataset's calibration page
# (cvg.cit.tum.de/data/datasets/rgbd-dataset/intrinsic_calibration): the OpenNI driver undistorts the images with
# the sensor's factory calibration and reprojects the depth images into the colour camera's frame, so "the
# conversion from the 2D images to 3D point clouds is the same for all datasets" with these values, and the
# file-format page recommends them "without undistortion, as undistortion of the pre-registered depth images
# is not trivial". Unprojecting with a colour calibration instead would scale points' x and y against the
# depth sensor's own geometry: by 525/517.3 (+1.5 %, freiburg1) down to 525/539.2 (−2.6 %, freiburg3's y).
TUM_DEPTH_CAMERA = (525.0, 525.0, 319.5, 239.5)
TUM_IMAGE_SIZE = (480, 640)   # H, W of the frames TUM_DEPTH_CAMERA describes
DEPTH_SCALE = 5000.0
MAX_GAP_FACTOR = 1.5   # a step longer than this × the median step between kept frames is a gap


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """`timestamp filename` lines -> (N float64 timestamps, N filenames), sorted by time."""
    require_file(path, "TUM file list")
    stamps, names = [], []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            stamps.append(float(fields[0]))
        except ValueError:
            raise DataError(f"{path}:{n}: bad timestamp {fields[0]!r}") from None
        if len(fields) < 2:
            raise DataError(f"{path}:{n}: expected `timestamp filename`")
        names.append(fields[1])
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps, np.float64)[order], [names[i] for i in order]


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """groundtruth.txt -> (N timestamps, N×4×4 world_T_cam float64), sorted by time."""
    require_file(path, "TUM groundtruth.txt")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 8:
            raise DataError(f"{path}:{n}: expected `timestamp tx ty tz qx qy qz qw`, got {len(fields)} fields")
        try:
            rows.append([float(v) for v in fields])
        except ValueError:
            raise DataError(f"{path}:{n}: non-numeric pose") from None
    if not rows:
        raise DataError(f"{path}: no poses")
    data = np.array(rows, np.float64)
    data = data[np.argsort(data[:, 0], kind="stable")]
    t, (qx, qy, qz, qw) = data[:, 1:4], data[:, 4:8].T
    if not np.isfinite(data).all() or (np.abs(np.sqrt(qx**2 + qy**2 + qz**2 + qw**2) - 1) > 1e-2).any():
        raise DataError(f"{path}: poses must be finite with unit quaternions")
    q_wxyz = torch.as_tensor(np.stack([qw, qx, qy, qz], axis=1))  # N×4, (w, x, y, z)
    world_T_cam = se3.from_rt(se3.quaternion_to_matrix(q_wxyz), torch.as_tensor(t)).numpy()  # N×4×4
    return data[:, 0], world_T_cam


def nearest(stamps: np.ndarray, queries: np.ndarray, max_dt: float) -> np.ndarray:
    """Index of the nearest entry of sorted `stamps` for each query, or -1 if farther than max_dt."""
    if len(stamps) == 0:
        return np.full(len(queries), -1)
    right = np.clip(np.searchsorted(stamps, queries), 0, len(stamps) - 1)
    left = np.clip(right - 1, 0, len(stamps) - 1)
    pick = np.where(np.abs(stamps[left] - queries) <= np.abs(stamps[right] - queries), left, right)
    return np.where(np.abs(stamps[pick] - queries) <= max_dt, pick, -1)


def pair_one_to_one(a: np.ndarray, b: np.ndarray, max_dt: float) -> np.ndarray:
    """For each time of sorted `a`, the index of its partner in sorted `b` (-1: none): pairs within max_dt,
    closest first, each entry of `b` used at most once (TUM's associate.py)."""
    candidates = []
    for i, t in enumerate(a):
        lo, hi = np.searchsorted(b, t - max_dt, "left"), np.searchsorted(b, t + max_dt, "right")
        candidates += [(abs(float(b[j]) - float(t)), i, j) for j in range(lo, hi)]
    partner = np.full(len(a), -1)
    used = np.zeros(len(b), bool)
    for _, i, j in sorted(candidates):
        if partner[i] < 0 and not used[j]:
            partner[i], used[j] = j, True
    return partner


def associate(root: Path, max_dt: float) -> tuple[list[tuple[float, str, str, np.ndarray]], dict[str, int]]:
    """((rgb timestamp, rgb file, depth file, world_T_cam 4×4) of every rgb frame with a depth frame (one to one)
    and a pose within max_dt seconds, in time order; {rgb_frames, dropped_no_depth, dropped_no_pose})."""
    rgb_t, rgb_files = read_file_list(root / "rgb.txt")
    depth_t, depth_files = read_file_list(root / "depth.txt")
    pose_t, poses = read_groundtruth(root / "groundtruth.txt")
    d_idx = pair_one_to_one(rgb_t, depth_t, max_dt)
    p_idx = nearest(pose_t, rgb_t, max_dt)
    counts = {"rgb_frames": len(rgb_t), "dropped_no_depth": int((d_idx < 0).sum()),
              "dropped_no_pose": int(((d_idx >= 0) & (p_idx < 0)).sum())}
    return [(float(rgb_t[i]), rgb_files[i], depth_files[d_idx[i]], poses[p_idx[i]])
            for i in range(len(rgb_t)) if d_idx[i] >= 0 and p_idx[i] >= 0], counts


def tum_window_to_record(root: Path, frames: list[tuple[float, str, str, np.ndarray]],
                         pix_T_cam: np.ndarray, *, camera_size: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
    """T associated frames -> one record (V=1, K=0) with ref = the first camera. camera_size: (H, W) the frames
    must have (the default camera's: a resized copy would pass the principal-point check at half size)."""
    rgb = np.stack([read_rgb(root / f[1]) for f in frames])[:, None]                        # T×1×H×W×3
    depth = np.stack([read_depth_png(root / f[2], DEPTH_SCALE) for f in frames])[:, None]  # T×1×H×W
    if rgb.shape[2:4] != depth.shape[2:4]:
        raise DataError(f"{root}: rgb {rgb.shape[2:4]} and depth {depth.shape[2:4]} sizes differ "
                        f"(frame {frames[0][1]})")
    H, W = rgb.shape[2:4]
    if camera_size is not None and (H, W) != tuple(camera_size):
        raise DataError(f"{root}: the frames are {W}×{H}, but TUM's camera {TUM_DEPTH_CAMERA} is for "
                        f"{camera_size[1]}×{camera_size[0]} (frame {frames[0][1]}); give the images' own --intrinsics")
    if not (0 <= pix_T_cam[0, 2] < W and 0 <= pix_T_cam[1, 2] < H):   # e.g. the full-size camera on resized frames
        raise DataError(f"{root}: the principal point ({pix_T_cam[0, 2]:g}, {pix_T_cam[1, 2]:g}) lies outside the "
                        f"{W}×{H} images (frame {frames[0][1]}); give the images' own --intrinsics")
    world_T_cam = np.stack([f[3] for f in frames])[:, None]                               # T×1×4×4
    T = len(frames)
    return {
        "rgb": rgb,
        "depth": depth,
        "pix_T_cam": pix_T_cam[None].astype(np.float32),                                   # 1×4×4
        "world_T_cam": world_T_cam.astype(np.float32),
        "world_T_ref": np.repeat(world_T_cam[:1, 0], T, axis=0).astype(np.float32),        # T×4×4
        **empty_boxes(T),
    }


def import_tum(src: str | os.PathLike, out_dir: str | os.PathLike, *, num_frames: int = 2,
               frame_step: int = 1, stride: int | None = None,
               intrinsics: tuple[float, float, float, float] | None = None, max_dt: float = 0.02,
               split: str = "train", preset_name: str = "paper", grid: Mapping | None = None,
               limit: int | None = None, shard_bytes: int = DEFAULT_SHARD_BYTES, overwrite: bool = False,
               on_record: Callable[[int, str], None] | None = None) -> dict:
    """Convert one TUM RGB-D sequence directory into a dataset of T=num_frames windows (module docstring);
    intrinsics None: TUM_DEPTH_CAMERA."""
    root = Path(src)
    if not root.exists():
        raise DataError(f"TUM sequence directory {root} does not exist")
    if not root.is_dir():
        raise DataError(f"{root} is a file; a TUM sequence is a directory (rgb.txt, depth.txt, groundtruth.txt)")
    if num_frames < 1 or frame_step < 1 or (stride is not None and stride < 1):
        raise DataError("num_frames, frame_step and stride must be at least 1")
    stride = stride or num_frames
    default_camera = intrinsics is None
    intrinsics = TUM_DEPTH_CAMERA if default_camera else tuple(intrinsics)
    associated, counts = associate(root, max_dt)
    frames = associated[::frame_step]
    if len(frames) < num_frames:
        raise DataError(f"{root}: only {len(frames)} associated rgb/depth/pose frames "
                        f"(within {max_dt} s), fewer than T={num_frames}")
    fx, fy, cx, cy = intrinsics
    pix_T_cam = np.eye(4)
    pix_T_cam[0, 0], pix_T_cam[1, 1], pix_T_cam[0, 2], pix_T_cam[1, 2] = fx, fy, cx, cy
    steps = np.diff([f[0] for f in frames])                        # seconds between consecutive kept frames
    gap_s = MAX_GAP_FACTOR * float(np.median(steps)) if len(steps) else None
    windows = range(0, len(frames) - num_frames + 1, stride)
    starts = [s for s in windows if gap_s is None or (steps[s:s + num_frames - 1] <= gap_s).all()]
    sequence = record_key(root.resolve().name)

    def records() -> Iterator[dict]:
        for start in starts:
            rec = tum_window_to_record(root, frames[start:start + num_frames], pix_T_cam,
                                       camera_size=TUM_IMAGE_SIZE if default_camera else None)
            rec["__key__"] = f"{sequence}-{start:06d}"
            yield rec

    generator = {"source": "tum", "src": str(root.resolve()), "num_frames": num_frames,
                 "frame_step": frame_step, "stride": stride, "intrinsics": list(intrinsics),
                 "max_dt": max_dt, "associated_frames": len(frames), **counts,
                 "windows_skipped_for_gaps": len(windows) - len(starts), "gap_s": gap_s,
                 "largest_step_s": max((float(steps[s:s + num_frames - 1].max()) for s in starts
                                        if num_frames > 1), default=0.0),
                 "frame": "world = mocap world; ref = first camera of each record"}
    return write_imported(out_dir, records(), split=split, preset_name=preset_name, grid=grid,
                          generator=generator, limit=limit, shard_bytes=shard_bytes, overwrite=overwrite,
                          on_record=on_record)
