"""Helpers shared by the importers: file reading with clear errors, record keys, the writer call."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping

import numpy as np

from core.data.shards import DEFAULT_SHARD_BYTES, write_dataset
from core.errors import DataError


def record_key(name: str) -> str:
    """A WebDataset-safe record key ([A-Za-z0-9_-]+) from a file or sequence name."""
    key = re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")
    return key or "record"


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DataError(f"missing {what}: {path}")
    return path


def read_rgb(path: Path) -> np.ndarray:
    """H×W×3 uint8 from an image file (PIL; any mode converted to RGB)."""
    from PIL import Image, UnidentifiedImageError
    require_file(path, "image")
    try:
        with Image.open(path) as img:
            return np.asarray(img.convert("RGB"), dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError) as e:
        raise DataError(f"{path}: cannot read image: {e}") from None


def read_depth_png(path: Path, scale: float) -> np.ndarray:
    """H×W float32 metres from a 16-bit PNG holding depth·scale (0 = missing)."""
    from PIL import Image, UnidentifiedImageError
    require_file(path, "depth image")
    try:
        with Image.open(path) as img:
            raw = np.asarray(img)
    except (UnidentifiedImageError, OSError) as e:
        raise DataError(f"{path}: cannot read depth image: {e}") from None
    # 16-bit only: an 8-bit image (a depth map re-saved by an image tool) would read as depths of at most 255/scale
    # (5 cm for TUM's 5000) without a word; PIL reads 16-bit greys as uint16 or, for mode "I", int32 ≤ 65535
    if raw.ndim != 2 or not (raw.dtype == np.uint16 or (raw.dtype == np.int32 and raw.min(initial=0) >= 0
                                                         and raw.max(initial=0) <= 65535)):
        raise DataError(f"{path}: depth must be a single-channel 16-bit PNG, got {raw.dtype} {raw.shape}")
    return (raw.astype(np.float64) / scale).astype(np.float32)


def resize_rgb(rgb: np.ndarray, H: int, W: int) -> np.ndarray:
    """H0×W0×3 uint8 -> H×W×3 uint8 (bilinear)."""
    from PIL import Image
    return np.asarray(Image.fromarray(rgb).resize((W, H), Image.BILINEAR), dtype=np.uint8).copy()


def write_imported(out_dir: str | os.PathLike, records: Iterable[dict], *, split: str, preset_name: str,
                   grid: Mapping | None, generator: dict, limit: int | None, shard_bytes: int,
                   overwrite: bool, on_record: Callable[[int, str], None] | None) -> dict:
    """write_dataset for importers: grid from the preset when not given, at most `limit` records."""
    if grid is None:
        from core.presets import get_preset
        grid = get_preset(preset_name).grid.to_dict()

    def limited() -> Iterator[dict]:
        for i, rec in enumerate(records):
            if limit is not None and i >= limit:
                return
            yield rec

    return write_dataset(out_dir, limited(), split=split, preset_name=preset_name, grid=grid,
                         generator=generator, seed=None, shard_bytes=shard_bytes or DEFAULT_SHARD_BYTES,
                         overwrite=overwrite, on_record=on_record)
