"""Importer for the authors' npz files (GitHub aharley/neural_3d_mapping, CARLA multiview data).

One file holds S camera views at ONE time step:
    pix_T_cams     S×4×4   intrinsics
    origin_T_camXs S×4×4   camera poses in the world `origin`
    origin_T_camRs S×4×4   the gravity-aligned reference camera R (the same for every view)
    rgb_camXs      S×H×W×3 uint8
    xyz_camXs      S×N×3   point cloud of each view, in that camera (zero rows are padding)
    boxlists       S×N×9   (x, y, z, lx, ly, lz, rx, ry, rz): centre in camR, full lengths along the
                           object's axes, and roll/pitch/yaw in DEGREES relative to the origin
    tidlists       S×N     track ids (-1 = padding)
    scorelists     S×N     1 = a real box, 0 = padding
and becomes one record with T = 1, V = S; depth is rendered from xyz_camXs by z-buffer.

Box rotation (as the authors' `utils/misc.py::parse_boxes` reads their CARLA data): with
(roll, pitch, yaw) = radians(rx, ry, rz), origin_R_obj = Rz(yaw − π/2) · Ry(−roll) · Rx(−pitch − π/2)
(se3.euler_to_matrix order), and camR_R_obj = camR_T_origin[:3,:3] · origin_R_obj; the object's axes are
then (x: lx, y: ly down, z: lz) and the box yaw is read about camR's Y. Pitch/roll left after that (a
tilted object) are dropped: boxes carry only a yaw.

Frames: `world` = `ref` = camR of view 0 (gravity-aligned, Y down, so that the canonical yaw-about-Y
boxes can live in world); world_T_ref = I; world_T_cam = camR_T_origin · origin_T_camX.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Callable, Iterator, Mapping

import numpy as np
import torch

from core.data.importers._common import record_key, write_imported
from core.data.shards import DEFAULT_SHARD_BYTES
from core.errors import DataError
from core.geometry import se3
from core.geometry.camera import points_to_depth

AUTHORS_KEYS = ("pix_T_cams", "origin_T_camXs", "origin_T_camRs", "rgb_camXs", "xyz_camXs",
                "boxlists", "tidlists", "scorelists")


def load_authors_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of one authors' npz file, shape-checked; DataError naming the file and key."""
    path = Path(path)
    # np.load treats anything that is not a zip/.npy as a pickle and then says "pickled data"; name
    # the real problem instead.
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise DataError(f"{path}: cannot read: {e.strerror or e}") from None
    if magic[:2] != b"PK":
        raise DataError(f"{path} is not an .npz archive (a zip of .npy arrays, as the authors' files are)")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in AUTHORS_KEYS if k not in z.files]
            if missing:
                raise DataError(f"{path}: key '{missing[0]}' is missing (the authors' format has "
                                f"{', '.join(AUTHORS_KEYS)})")
            d = {k: z[k] for k in AUTHORS_KEYS}
    except DataError:
        raise
    except (ValueError, OSError, EOFError) as e:
        raise DataError(f"{path}: cannot read npz: {e}") from None
    S = d["pix_T_cams"].shape[0]
    expected = {"pix_T_cams": (S, 4, 4), "origin_T_camXs": (S, 4, 4), "origin_T_camRs": (S, 4, 4)}
    for k, shape in expected.items():
        if d[k].shape != shape:
            raise DataError(f"{path}: key '{k}': expected shape {shape}, got {d[k].shape}")
    rgb = d["rgb_camXs"]
    if rgb.ndim != 4 or rgb.shape[0] != S or rgb.shape[3] != 3 or rgb.dtype != np.uint8:
        raise DataError(f"{path}: key 'rgb_camXs': expected uint8 S×H×W×3 with S={S}, got {rgb.dtype} {rgb.shape}")
    if d["xyz_camXs"].ndim != 3 or d["xyz_camXs"].shape[0] != S or d["xyz_camXs"].shape[2] != 3:
        raise DataError(f"{path}: key 'xyz_camXs': expected S×N×3, got {d['xyz_camXs'].shape}")
    N = d["boxlists"].shape[1] if d["boxlists"].ndim == 3 else -1
    if d["boxlists"].shape != (S, N, 9):
        raise DataError(f"{path}: key 'boxlists': expected S×N×9, got {d['boxlists'].shape}")
    for k in ("tidlists", "scorelists"):
        if d[k].shape != (S, N):
            raise DataError(f"{path}: key '{k}': expected shape {(S, N)}, got {d[k].shape}")
    # One time step: the reference camera and the boxes are the same for every view (entry 0 is what is read).
    # The authors' *sequence* files have the same keys with S time steps, a camR and boxes per step: read as
    # one instant they would fuse frames of different times as simultaneous views.
    for k, tol in (("origin_T_camRs", 1e-4), ("boxlists", 1e-4), ("tidlists", 0), ("scorelists", 0)):
        first = d[k][:1].astype(np.float64)
        if not np.allclose(d[k].astype(np.float64), first, rtol=0.0, atol=tol):
            s = int(np.flatnonzero(~np.isclose(d[k].astype(np.float64), first, rtol=0.0, atol=tol)
                                    .reshape(S, -1).all(axis=1))[0])
            raise DataError(f"{path}: key '{k}' differs between entry 0 and entry {s}: this importer reads files "
                            "of one time step (S views, one reference camera and one box list); the authors' "
                            "sequence files hold S time steps")
    return d


def authors_boxes_to_canonical(boxlist: np.ndarray, camR_T_origin: np.ndarray) -> np.ndarray:
    """N×9 authors' boxes (centre in camR, lengths, degrees w.r.t. origin) -> N×7 canonical in camR."""
    b = torch.as_tensor(boxlist, dtype=torch.float64)
    roll, pitch, yaw = torch.deg2rad(b[:, 6]), torch.deg2rad(b[:, 7]), torch.deg2rad(b[:, 8])
    origin_R_obj = se3.euler_to_matrix(-pitch - math.pi / 2, -roll, yaw - math.pi / 2)  # N×3×3
    camR_R_obj = torch.as_tensor(camR_T_origin[:3, :3], dtype=torch.float64) @ origin_R_obj  # N×3×3
    box_yaw = se3.matrix_to_yaw(camR_R_obj)  # N
    return torch.cat([b[:, :6], box_yaw[:, None]], dim=1).numpy()  # N×7


def authors_npz_to_record(d: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One authors' file (load_authors_npz) -> one record (T=1, V=S) in world = camR of view 0."""
    S, H, W, _ = d["rgb_camXs"].shape
    origin_T_camR = d["origin_T_camRs"][0].astype(np.float64)
    camR_T_origin = np.linalg.inv(origin_T_camR)
    world_T_cam = camR_T_origin[None] @ d["origin_T_camXs"].astype(np.float64)  # S×4×4

    pix_T_cam = torch.as_tensor(d["pix_T_cams"], dtype=torch.float32)
    xyz = torch.as_tensor(d["xyz_camXs"], dtype=torch.float32)  # S×N×3
    depth = points_to_depth(xyz, pix_T_cam, H, W).numpy()  # S×H×W

    score, tid = d["scorelists"][0], d["tidlists"][0]
    valid = (score > 0) & (tid != -1)
    boxes = authors_boxes_to_canonical(d["boxlists"][0], camR_T_origin)
    boxes[~valid] = 0.0
    return {
        "rgb": d["rgb_camXs"][None],                                    # 1×S×H×W×3
        "depth": depth[None].astype(np.float32),                        # 1×S×H×W
        "pix_T_cam": d["pix_T_cams"].astype(np.float32),                # S×4×4
        "world_T_cam": world_T_cam[None].astype(np.float32),            # 1×S×4×4
        "world_T_ref": np.eye(4, dtype=np.float32)[None],               # 1×4×4
        "boxes": boxes[None].astype(np.float32),                        # 1×K×7
        "box_valid": valid[None].astype(np.bool_),                      # 1×K
        "box_id": tid.astype(np.int32),                                 # K
        "box_moving": np.zeros(tid.shape, np.bool_),                    # K (one time step: unknown)
    }


def list_authors_files(src: str | os.PathLike) -> list[Path]:
    src = Path(src)
    if src.is_file():
        return [src]
    if not src.is_dir():
        raise DataError(f"authors' npz source {src} does not exist")
    files = sorted(src.glob("*.npz"))
    if not files:
        raise DataError(f"no .npz files in {src}")
    return files


def import_authors_npz(src: str | os.PathLike, out_dir: str | os.PathLike, *, split: str = "train",
                       preset_name: str = "paper", grid: Mapping | None = None, limit: int | None = None,
                       shard_bytes: int = DEFAULT_SHARD_BYTES, overwrite: bool = False,
                       on_record: Callable[[int, str], None] | None = None) -> dict:
    """Convert an authors' .npz file, or a directory of them (sorted by name), into a dataset."""
    files = list_authors_files(src)

    def records() -> Iterator[dict]:
        for path in files:
            rec = authors_npz_to_record(load_authors_npz(path))
            rec["__key__"] = record_key(path.stem)
            yield rec

    generator = {"source": "authors-npz", "src": str(Path(src).resolve()), "files": len(files),
                 "frame": "world = ref = camR of view 0"}
    return write_imported(out_dir, records(), split=split, preset_name=preset_name, grid=grid,
                          generator=generator, limit=limit, shard_bytes=shard_bytes, overwrite=overwrite,
                          on_record=on_record)
