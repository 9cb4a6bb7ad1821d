"""Importer for KITTI object detection (training split with labels).

Layout read:
    <root>/training/image_2/<id>.png     left colour camera (rectified)
    <root>/training/velodyne/<id>.bin    float32 N×4 (x, y, z, reflectance) in the Velodyne frame
    <root>/training/calib/<id>.txt       P0..P3 (3×4), R0_rect (3×3), Tr_velo_to_cam (3×4), ...
    <root>/training/label_2/<id>.txt     type trunc occ alpha x1 y1 x2 y2 h w l x y z ry
    <root>/ImageSets/{train,val}.txt     frame ids of the usual 3712 / 3769 split

One record per frame, T = 1, V = 1. Frames: `world` = `ref` = the rectified reference camera (rect
cam0), the frame KITTI's labels are written in, so boxes are exactly
core.geometry.boxes.kitti_to_boxes(label rows); the image_2 camera sits at world_T_cam = [I | −t2],
where P2 = K2·[I | t2] (t2 ≈ 6 cm along x). Velodyne points go to rect cam0 by R0_rect·Tr_velo_to_cam,
then to cam2 by + t2, and are z-buffered into depth with K2 (core.geometry.camera.points_to_depth).
Labels of type DontCare are dropped; box ids are the label rows' order; nothing is marked moving.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import torch

from core.data.importers._common import read_rgb, record_key, require_file, resize_rgb, write_imported
from core.data.shards import DEFAULT_SHARD_BYTES
from core.errors import DataError
from core.geometry.boxes import kitti_to_boxes
from core.geometry.camera import points_to_depth, scale_intrinsics


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """KITTI calib file -> {'P2': 3×4, 'R0_rect': 3×3, 'Tr_velo_to_cam': 3×4, ...} (float64)."""
    require_file(path, "KITTI calib file")
    shapes = {"R0_rect": (3, 3)}
    calib: dict[str, np.ndarray] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if ":" not in line:
            continue
        name, values = line.split(":", 1)
        try:
            numbers = np.array([float(v) for v in values.split()], np.float64)
        except ValueError:
            raise DataError(f"{path}:{n}: non-numeric calibration values for {name.strip()}") from None
        shape = shapes.get(name.strip(), (3, 4))
        if numbers.size != shape[0] * shape[1]:
            raise DataError(f"{path}:{n}: {name.strip()} needs {shape[0] * shape[1]} numbers, got {numbers.size}")
        calib[name.strip()] = numbers.reshape(shape)
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        if key not in calib:
            raise DataError(f"{path}: calibration entry {key} is missing")
    return calib


def read_labels(path: Path, classes: Sequence[str] | None = None) -> tuple[list[str], np.ndarray]:
    """KITTI label file -> (types, K×7 rows (h, w, l, x, y_bottom, z, ry)); DontCare dropped."""
    require_file(path, "KITTI label file")
    types: list[str] = []
    rows: list[list[float]] = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 15:
            raise DataError(f"{path}:{n}: a label line has 15 fields, got {len(fields)}")
        kind = fields[0]
        if kind == "DontCare" or (classes is not None and kind not in classes):
            continue
        try:
            rows.append([float(v) for v in fields[8:15]])
        except ValueError:
            raise DataError(f"{path}:{n}: non-numeric box fields") from None
        types.append(kind)
    return types, np.array(rows, np.float64).reshape(-1, 7)


def read_split(root: Path, split: str) -> list[str]:
    """Frame ids of ImageSets/<split>.txt."""
    path = require_file(root / "ImageSets" / f"{split}.txt", f"KITTI split list '{split}'")
    ids = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    if not ids:
        raise DataError(f"{path}: the split list is empty")
    return ids


def kitti_frame_to_record(root: Path, frame_id: str, *, resize: tuple[int, int] | None = None,
                          classes: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """One KITTI frame -> one record (T=1, V=1) in world = rect cam0 (see the module docstring)."""
    training = root / "training"
    rgb = read_rgb(training / "image_2" / f"{frame_id}.png")  # H0×W0×3
    calib = read_calib(training / "calib" / f"{frame_id}.txt")
    velo_path = require_file(training / "velodyne" / f"{frame_id}.bin", "KITTI velodyne scan")
    raw = np.fromfile(velo_path, dtype=np.float32)
    if raw.size % 4:
        raise DataError(f"{velo_path}: size is not a multiple of 4 float32 (x, y, z, reflectance)")
    xyz_velo = raw.reshape(-1, 4)[:, :3].astype(np.float64)  # N×3
    _types, kitti = read_labels(training / "label_2" / f"{frame_id}.txt", classes)

    K2 = calib["P2"][:, :3]
    t2 = np.linalg.solve(K2, calib["P2"][:, 3])           # P2 = K2·[I | t2]
    rect_T_velo = np.eye(4)
    rect_T_velo[:3, :] = calib["R0_rect"] @ calib["Tr_velo_to_cam"]  # 3×4
    xyz_cam2 = xyz_velo @ rect_T_velo[:3, :3].T + rect_T_velo[:3, 3] + t2  # N×3

    pix_T_cam = np.eye(4)
    pix_T_cam[:3, :3] = K2
    H0, W0 = rgb.shape[:2]
    H, W = resize if resize is not None else (H0, W0)
    pix_T_cam_t = torch.as_tensor(pix_T_cam, dtype=torch.float64)[None]  # 1×4×4
    if (H, W) != (H0, W0):
        pix_T_cam_t = scale_intrinsics(pix_T_cam_t, W / W0, H / H0)
        rgb = resize_rgb(rgb, H, W)
    depth = points_to_depth(torch.as_tensor(xyz_cam2)[None], pix_T_cam_t, H, W)  # 1×H×W

    world_T_cam = np.eye(4)
    world_T_cam[:3, 3] = -t2
    boxes = kitti_to_boxes(torch.as_tensor(kitti)).numpy()  # K×7 in rect cam0 = world
    K = boxes.shape[0]
    return {
        "rgb": rgb[None, None],                                          # 1×1×H×W×3
        "depth": depth.numpy()[None].astype(np.float32),                 # 1×1×H×W
        "pix_T_cam": pix_T_cam_t.numpy().astype(np.float32),             # 1×4×4
        "world_T_cam": world_T_cam[None, None].astype(np.float32),       # 1×1×4×4
        "world_T_ref": np.eye(4, dtype=np.float32)[None],                # 1×4×4
        "boxes": boxes[None].astype(np.float32),                         # 1×K×7
        "box_valid": np.ones((1, K), np.bool_),                          # 1×K
        "box_id": np.arange(K, dtype=np.int32),                          # K
        "box_moving": np.zeros(K, np.bool_),                             # K
    }


def import_kitti(src: str | os.PathLike, out_dir: str | os.PathLike, *, split: str = "train",
                 preset_name: str = "paper", grid: Mapping | None = None, limit: int | None = None,
                 resize: tuple[int, int] | None = None, classes: Sequence[str] | None = None,
                 shard_bytes: int = DEFAULT_SHARD_BYTES, overwrite: bool = False,
                 on_record: Callable[[int, str], None] | None = None) -> dict:
    """Convert the frames of ImageSets/<split>.txt of a KITTI object root into a dataset.

    resize: (H, W) to resample every image to (KITTI frames differ by a few pixels, and a batch needs
    one size); classes: keep only these label types (default: all but DontCare).
    """
    root = Path(src)
    if not (root / "training").is_dir():
        raise DataError(f"{root} is not a KITTI object root (no training/ directory)")
    ids = read_split(root, split)

    def records() -> Iterator[dict]:
        for frame_id in ids:
            rec = kitti_frame_to_record(root, frame_id, resize=resize, classes=classes)
            rec["__key__"] = record_key(frame_id)
            yield rec

    generator = {"source": "kitti", "src": str(root.resolve()), "split_list": f"ImageSets/{split}.txt",
                 "frames": len(ids), "resize": list(resize) if resize else None,
                 "classes": list(classes) if classes else "all but DontCare",
                 "frame": "world = ref = rectified camera 0 (label frame)"}
    return write_imported(out_dir, records(), split=split, preset_name=preset_name, grid=grid,
                          generator=generator, limit=limit, shard_bytes=shard_bytes, overwrite=overwrite,
                          on_record=on_record)
