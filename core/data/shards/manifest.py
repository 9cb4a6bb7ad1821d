"""Reading and checking a dataset directory's manifest, and the checked list of its shards."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from core.data.shards.layout import FORMAT_NAME, MANIFEST_NAME, SCHEMA_VERSION, SHARD_NAME_RE, one_line
from core.errors import DataError


def load_manifest(root: str | os.PathLike) -> dict:
    """Read and structurally check `<root>/manifest.json`; DataError if absent or malformed."""
    root = Path(root)
    if not root.exists():
        raise DataError(f"dataset directory {root} does not exist")
    if not root.is_dir():
        raise DataError(f"{root} is not a directory")
    path = root / MANIFEST_NAME
    if not path.is_file():
        raise DataError(f"{root} has no {MANIFEST_NAME} (not an n3dmap dataset, or an unfinished write)")
    try:
        manifest = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: not valid JSON: {one_line(e)}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT_NAME:
        raise DataError(f"{path}: not an n3dmap dataset manifest (format != {FORMAT_NAME!r})")
    if manifest.get("schema_version") != SCHEMA_VERSION:
        raise DataError(f"{path}: schema version {manifest.get('schema_version')!r} is not supported "
                        f"(this n3dmap reads version {SCHEMA_VERSION})")
    shards = manifest.get("shards")
    if not isinstance(shards, list):
        raise DataError(f"{path}: 'shards' must be a list")
    total = 0
    for i, entry in enumerate(shards):
        ok = (isinstance(entry, dict) and isinstance(entry.get("filename"), str)
              and SHARD_NAME_RE.match(entry["filename"]) and isinstance(entry.get("keys"), list)
              and entry.get("num_records") == len(entry["keys"]) and isinstance(entry.get("bytes"), int)
              and isinstance(entry.get("sha256"), str))
        if not ok:
            raise DataError(f"{path}: shard entry {i} is malformed "
                            "(needs filename, num_records == len(keys), keys, bytes, sha256)")
        total += entry["num_records"]
    if manifest.get("num_records") != total:
        raise DataError(f"{path}: num_records {manifest.get('num_records')!r} != sum over shards ({total})")
    _check_grid(manifest.get("grid"), path)
    _check_dims(manifest.get("dims"), path)
    return manifest


GRID_SIZES, GRID_BOUNDS = ("Z", "Y", "X"), ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")


def _check_grid(grid, path: Path) -> None:
    """The optional 'grid' (the map grid the records were made for; `data info`, previews): positive int sizes
    Z, Y, X and numeric bounds, each min below its max."""
    if grid is None:
        return
    ok = (isinstance(grid, dict)
          and all(type(grid.get(k)) is int and grid[k] > 0 for k in GRID_SIZES)
          and all(isinstance(grid.get(k), (int, float)) and not isinstance(grid.get(k), bool) for k in GRID_BOUNDS)
          and all(grid[f"{a}min"] < grid[f"{a}max"] for a in "xyz"))
    if not ok:
        raise DataError(f"{path}: 'grid' is malformed (needs positive integer {', '.join(GRID_SIZES)} and "
                        f"{', '.join(GRID_BOUNDS)} with each min < max), got {grid!r}")


def _check_dims(dims, path: Path) -> None:
    """The optional 'dims': each named size's [min, max] over the records, non-negative integers."""
    if dims is None:
        return
    ok = isinstance(dims, dict) and all(
        isinstance(v, list) and len(v) == 2 and all(type(x) is int and x >= 0 for x in v) and v[0] <= v[1]
        for v in dims.values())
    if not ok:
        raise DataError(f"{path}: 'dims' is malformed (each size needs [min, max], integers, min <= max), got {dims!r}")


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def dataset_shard_paths(data_dir: str | os.PathLike) -> tuple[list[str], dict[str, list[str]], dict]:
    """Check a dataset directory for a streaming reader: (absolute shard paths, the manifest's record keys
    per shard filename, manifest). DataError for a missing shard, one whose size differs from the manifest's, or
    a manifest without shards."""
    root = Path(data_dir)
    manifest = load_manifest(root)
    paths, keys = [], {}
    for entry in manifest["shards"]:
        path = root / entry["filename"]
        if not path.is_file():
            raise DataError(f"missing shard {entry['filename']} (listed in {root / MANIFEST_NAME})")
        size = path.stat().st_size
        if size != entry["bytes"]:   # as ShardDataset checks: a shard cut short or changed since it was written
            raise DataError(f"{entry['filename']}: size {size} bytes differs from the manifest's {entry['bytes']} "
                            "(truncated or changed shard)")
        paths.append(str(path.resolve()))
        keys[entry["filename"]] = list(entry["keys"])
    if not paths:
        raise DataError(f"{root}: the manifest lists no shards")
    return paths, keys, manifest

