"""Writing a dataset directory: validated records into tar shards, then the manifest, atomically.

Shards are written under temporary names (`.partial`) and renamed when every record is in; the manifest
goes last, so a directory with a manifest holds a complete dataset.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tarfile
from pathlib import Path
from typing import BinaryIO, Callable, Iterable, Mapping

import numpy as np

from core.data.record import RECORD_SCHEMA, validate_record
from core.data.shards.codec import encode_record
from core.data.shards.layout import (DEFAULT_SHARD_BYTES, FORMAT_NAME, KEY_FIELD, MANIFEST_NAME, PARTIAL_SUFFIX,
                                     RECORD_KEY_RE, SCHEMA_VERSION, SHARD_NAME_RE, member_bytes, one_line,
                                     shard_filename)
from core.errors import DataError


class _HashingWriter:
    """A write-only file wrapper that hashes (sha256) and counts what passes through it."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self.sha256 = hashlib.sha256()
        self.nbytes = 0

    def write(self, b: bytes) -> int:
        self._f.write(b)
        self.sha256.update(b)
        self.nbytes += len(b)
        return len(b)

    def tell(self) -> int:
        return self.nbytes

    def flush(self) -> None:
        self._f.flush()


class _ShardWriter:
    """Writes one shard to a temporary name; `close()` returns its manifest entry."""

    def __init__(self, out_dir: Path, index: int) -> None:
        self.filename = shard_filename(index)
        self.tmp_path = out_dir / (self.filename + PARTIAL_SUFFIX)
        self._file = open(self.tmp_path, "wb")
        try:
            self._hasher = _HashingWriter(self._file)
            # USTAR with fixed owner/mtime: the same records give byte-identical shards (same sha256).
            self._tar = tarfile.open(fileobj=self._hasher, mode="w", format=tarfile.USTAR_FORMAT)
        except BaseException:
            self.abort()
            raise
        self.keys: list[str] = []
        self.payload_bytes = 0

    def add(self, key: str, payload: bytes) -> None:
        info = tarfile.TarInfo(name=f"{key}.npz")
        info.size = len(payload)
        info.mtime = 0
        info.mode = 0o644
        info.uid = info.gid = 0
        info.uname = info.gname = ""
        self._tar.addfile(info, io.BytesIO(payload))
        self.keys.append(key)
        self.payload_bytes += member_bytes(len(payload))

    def close(self) -> dict:
        self._tar.close()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        return {"filename": self.filename, "num_records": len(self.keys), "keys": list(self.keys),
                "bytes": self._hasher.nbytes, "sha256": self._hasher.sha256.hexdigest()}

    def abort(self) -> None:
        try:
            self._file.close()
        finally:
            self.tmp_path.unlink(missing_ok=True)


def _is_dataset_file(name: str) -> bool:
    return name == MANIFEST_NAME or bool(SHARD_NAME_RE.match(name)) or name.endswith(PARTIAL_SUFFIX)


def _remove_partials(out: Path) -> None:
    for partial in out.glob("*" + PARTIAL_SUFFIX):
        partial.unlink(missing_ok=True)


def check_output_dir(out_dir: str | os.PathLike, *, overwrite: bool) -> None:
    """DataError unless `out_dir` is absent, an empty directory, or `overwrite` is set (a cheap check
    callers run before expensive work; write_dataset runs it again)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out} exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise DataError(f"{out} is not empty; choose an empty directory or replace it (--overwrite)")


def write_dataset(out_dir: str | os.PathLike, records: Iterable[Mapping[str, np.ndarray]], *,
                  split: str, preset_name: str, grid: Mapping, generator: Mapping, seed: int | None,
                  shard_bytes: int = DEFAULT_SHARD_BYTES, overwrite: bool = False,
                  on_record: Callable[[int, str], None] | None = None) -> dict:
    """Validate and write `records` as a sharded dataset in `out_dir`; return the manifest.

    records: dicts of the record schema (core.data.record), optionally with `"__key__"`: str.
    grid / generator: JSON-serialisable dicts stored in the manifest (the map grid; the parameters
    that made the data, e.g. {"source": "synthetic", "moving_ego": "off", ...}).
    shard_bytes: a new shard starts when the next record would push the current one past this size
    (a single larger record gets a shard of its own).
    on_record(count_written, key): called after each record is written (progress bars).

    Shards are written under temporary names and renamed when all records are in; `manifest.json` is
    written last, so a dataset directory with a manifest is complete. A non-empty `out_dir` is refused
    unless `overwrite=True`, which replaces the dataset files there (manifest.json, shard-*.tar) and
    leaves any other file alone. An invalid record raises DataError and leaves `out_dir` as it was.
    """
    out = Path(out_dir)
    if shard_bytes <= 0:
        raise DataError(f"shard_bytes must be positive, got {shard_bytes}")
    check_output_dir(out, overwrite=overwrite)
    out.mkdir(parents=True, exist_ok=True)
    _remove_partials(out)  # left by an earlier writer that was killed
    try:
        json.dumps({"grid": grid, "generator": generator, "seed": seed})
    except (TypeError, ValueError) as e:
        raise DataError(f"grid, generator and seed must be JSON-serialisable: {one_line(e)}") from None

    shards: list[dict] = []
    seen_keys: set[str] = set()
    dims_range: dict[str, list[int]] = {}
    writer: _ShardWriter | None = None
    count = 0
    try:
        for i, rec in enumerate(records):
            if not isinstance(rec, Mapping):
                raise DataError(f"record {i}: a record must be a dict of arrays, got {type(rec).__name__}")
            key = rec.get(KEY_FIELD, f"ep{i:06d}")
            where = f"record {i} ({key})"
            if not isinstance(key, str) or not RECORD_KEY_RE.match(key):
                raise DataError(f"{where}: record key must match [A-Za-z0-9_-]+, got {key!r}")
            if key in seen_keys:
                raise DataError(f"{where}: duplicate record key {key!r}")
            seen_keys.add(key)
            arrays = {k: v for k, v in rec.items() if k != KEY_FIELD}
            dims = validate_record(arrays, where)
            for name, size in dims.items():
                lo_hi = dims_range.setdefault(name, [size, size])
                lo_hi[0], lo_hi[1] = min(lo_hi[0], size), max(lo_hi[1], size)
            payload = encode_record(arrays)
            if writer is not None and writer.keys and \
                    writer.payload_bytes + member_bytes(len(payload)) > shard_bytes:
                shards.append(writer.close())
                writer = None
            if writer is None:
                writer = _ShardWriter(out, len(shards))
            writer.add(key, payload)
            count += 1
            if on_record is not None:
                on_record(count, key)
        if writer is not None:
            shards.append(writer.close())
            writer = None
    except BaseException:
        if writer is not None:
            writer.abort()
        # Every temporary file in `out` is this call's (stale ones went above). Sweeping them all, not
        # just those of `writer` and `shards`, also removes a shard whose writer was interrupted (Ctrl-C)
        # after creating its file but before being assigned: CI hit that window once.
        _remove_partials(out)
        raise
    if count == 0:
        raise DataError("no records to write (the record source was empty)")

    manifest = {
        "format": FORMAT_NAME,
        "schema_version": SCHEMA_VERSION,
        "preset": preset_name,
        "grid": dict(grid),
        "generator": dict(generator),
        "seed": seed,
        "split": split,
        "num_records": count,
        "record_schema": {k: {"dtype": str(dt), "shape": [str(d) for d in named]}
                          for k, (dt, named) in RECORD_SCHEMA.items()},
        "dims": dims_range,
        "shards": shards,
    }
    # Old dataset files go first so a crash between here and the manifest leaves no stale manifest
    # pointing at replaced shards (and an interrupt no temporary file: the directory then holds no dataset).
    try:
        for old in out.iterdir():
            if _is_dataset_file(old.name) and not old.name.endswith(PARTIAL_SUFFIX):
                old.unlink()
        for entry in shards:
            os.replace(out / (entry["filename"] + PARTIAL_SUFFIX), out / entry["filename"])
        tmp_manifest = out / (MANIFEST_NAME + PARTIAL_SUFFIX)
        tmp_manifest.write_text(json.dumps(manifest, indent=1) + "\n")
        os.replace(tmp_manifest, out / MANIFEST_NAME)
    except BaseException:
        _remove_partials(out)
        raise
    return manifest
