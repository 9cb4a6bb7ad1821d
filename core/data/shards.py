"""Datasets on disk: `manifest.json` + tar shards in WebDataset layout (docs/data.md#shards-and-manifest).

A dataset directory holds

    manifest.json        schema version, preset, grid, generator parameters and seed, split,
                         total records, per shard: filename, record count, record keys, bytes, sha256
    shard-00000.tar      members `<record_key>.npz`, one per record, each written by `np.savez`
    shard-00001.tar      (uncompressed, no pickled objects) and holding that record's arrays
    ...

Record keys match `[A-Za-z0-9_-]+` (WebDataset splits a member name at its first dot); by default
record i is keyed `ep{i:06d}`, and a record dict may carry its own key under `"__key__"`.

Readers: `ShardDataset` (random access by index through a per-shard member offset index, sequential
streaming, `verify()`), and the low-level pieces a streaming reader (the Ray Data one in
services.training.data) is built from: `dataset_shard_paths` (the checked shard list), `iter_tar_members`
(the checked, undecoded members of one shard), `iter_shard` and `decode_record`. Anything wrong —
missing manifest or shard, a shard whose size or sha256 differs from the manifest, a truncated tar, an undecodable member, a record that breaks the schema — raises
`DataError` naming the shard (and the record where known); a partial result is never passed on.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import tarfile
import zipfile
from pathlib import Path
from typing import BinaryIO, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np

from core.data.record import RECORD_KEYS, RECORD_SCHEMA, validate_record
from core.errors import DataError

FORMAT_NAME = "n3dmap-shards"
SCHEMA_VERSION = 1
MANIFEST_NAME = "manifest.json"
DEFAULT_SHARD_BYTES = 256 << 20
KEY_FIELD = "__key__"

_KEY_RE = re.compile(r"^[A-Za-z0-9_-]+$")
_SHARD_RE = re.compile(r"^shard-\d{5,}\.tar$")
_PARTIAL_SUFFIX = ".partial"
_TAR_BLOCK = 512


def shard_filename(index: int) -> str:
    """Filename of shard `index`: shard-00000.tar, shard-00001.tar, ..."""
    return f"shard-{index:05d}.tar"


def _one_line(e: BaseException) -> str:
    text = str(e) or type(e).__name__
    return " ".join(text.split())


# ----------------------------------------------------------------------------- records <-> bytes

def encode_record(rec: Mapping[str, np.ndarray]) -> bytes:
    """The npz bytes of one record (np.savez, uncompressed; keys in schema order)."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.ascontiguousarray(rec[k]) for k in RECORD_KEYS})
    return buf.getvalue()


def decode_record(npz_bytes: bytes, where: str) -> dict[str, np.ndarray]:
    """Decode one `<key>.npz` member into a validated record (never unpickles anything).

    Raises DataError("<where>: ...") if the bytes are not an npz archive, fail their CRC, hold pickled
    objects, or do not satisfy the record schema (core.data.record.validate_record).
    """
    try:
        loaded = np.load(io.BytesIO(npz_bytes), allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise DataError(f"{where}: not an npz archive (a single .npy array)")
        with loaded:
            rec = {name: loaded[name] for name in loaded.files}
    except DataError:
        raise
    except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as e:
        raise DataError(f"{where}: cannot decode npz: {_one_line(e)}") from None
    validate_record(rec, where)
    return rec


# ----------------------------------------------------------------------------- writing

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
        self.tmp_path = out_dir / (self.filename + _PARTIAL_SUFFIX)
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
        self.payload_bytes += _member_bytes(len(payload))

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


def _member_bytes(payload_size: int) -> int:
    """Bytes a member takes in a tar: one header block plus the payload padded to whole blocks."""
    return _TAR_BLOCK + -(-payload_size // _TAR_BLOCK) * _TAR_BLOCK


def _is_dataset_file(name: str) -> bool:
    return name == MANIFEST_NAME or bool(_SHARD_RE.match(name)) or name.endswith(_PARTIAL_SUFFIX)


def _remove_partials(out: Path) -> None:
    for partial in out.glob("*" + _PARTIAL_SUFFIX):
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
        raise DataError(f"grid, generator and seed must be JSON-serialisable: {_one_line(e)}") from None

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
            if not isinstance(key, str) or not _KEY_RE.match(key):
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
                    writer.payload_bytes + _member_bytes(len(payload)) > shard_bytes:
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
            if _is_dataset_file(old.name) and not old.name.endswith(_PARTIAL_SUFFIX):
                old.unlink()
        for entry in shards:
            os.replace(out / (entry["filename"] + _PARTIAL_SUFFIX), out / entry["filename"])
        tmp_manifest = out / (MANIFEST_NAME + _PARTIAL_SUFFIX)
        tmp_manifest.write_text(json.dumps(manifest, indent=1) + "\n")
        os.replace(tmp_manifest, out / MANIFEST_NAME)
    except BaseException:
        _remove_partials(out)
        raise
    return manifest


# ----------------------------------------------------------------------------- reading

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
        raise DataError(f"{path}: not valid JSON: {_one_line(e)}") from None
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
              and _SHARD_RE.match(entry["filename"]) and isinstance(entry.get("keys"), list)
              and entry.get("num_records") == len(entry["keys"]) and isinstance(entry.get("bytes"), int)
              and isinstance(entry.get("sha256"), str))
        if not ok:
            raise DataError(f"{path}: shard entry {i} is malformed "
                            "(needs filename, num_records == len(keys), keys, bytes, sha256)")
        total += entry["num_records"]
    if manifest.get("num_records") != total:
        raise DataError(f"{path}: num_records {manifest.get('num_records')!r} != sum over shards ({total})")
    return manifest


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def dataset_shard_paths(data_dir: str | os.PathLike) -> tuple[list[str], dict[str, list[str]], dict]:
    """Check a dataset directory for a streaming reader: (absolute shard paths, the manifest's record keys
    per shard filename, manifest). DataError for a missing shard or a manifest without shards."""
    root = Path(data_dir)
    manifest = load_manifest(root)
    paths, keys = [], {}
    for entry in manifest["shards"]:
        path = root / entry["filename"]
        if not path.is_file():
            raise DataError(f"missing shard {entry['filename']} (listed in {root / MANIFEST_NAME})")
        paths.append(str(path.resolve()))
        keys[entry["filename"]] = list(entry["keys"])
    if not paths:
        raise DataError(f"{root}: the manifest lists no shards")
    return paths, keys, manifest


def iter_shard(source: str | os.PathLike | bytes | BinaryIO, *, name: str | None = None,
               expected_keys: Sequence[str] | None = None) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
    """Stream the records of one shard: yields (record_key, record), each decoded and validated.

    source: a shard path, its bytes (e.g. from Ray Data `read_binary_files`), or a binary file object.
    name: how errors name the shard (default: the file's basename, else "shard").
    expected_keys: the record keys the manifest lists for this shard, in order; when given, a missing,
    extra or reordered member (e.g. a tar truncated at a member boundary) raises DataError.
    """
    if name is None:
        name = os.path.basename(os.fspath(source)) if isinstance(source, (str, os.PathLike)) else "shard"
    if isinstance(source, (str, os.PathLike)):
        if not os.path.isfile(source):
            raise DataError(f"missing shard {name} ({os.fspath(source)})")
        with open(source, "rb") as f:
            yield from _iter_tar(f, name, expected_keys)
    elif isinstance(source, (bytes, bytearray, memoryview)):
        yield from _iter_tar(io.BytesIO(bytes(source)), name, expected_keys)
    else:
        yield from _iter_tar(source, name, expected_keys)


def _iter_tar(f: BinaryIO, name: str, expected_keys: Sequence[str] | None):
    for key, payload in iter_tar_members(f, name, expected_keys):
        yield key, decode_record(payload, f"{name} record {key}")


def iter_tar_members(f: BinaryIO, name: str,
                     expected_keys: Sequence[str] | None = None) -> Iterator[tuple[str, bytes]]:
    """Stream the `(record_key, npz bytes)` members of one shard's tar file object, undecoded (a Ray Data
    reader splits shards on its read tasks and decodes on the workers; iter_shard decodes here).

    Every member must be a `<key>.npz` file with a valid key; given `expected_keys` (the manifest's, in
    order) a missing, extra or reordered member raises DataError, as does a truncated or corrupt tar.
    """
    position = 0
    try:
        with tarfile.open(fileobj=f, mode="r|") as tar:
            for member in tar:
                key = _member_key(member, name)
                if expected_keys is not None:
                    if position >= len(expected_keys):
                        raise DataError(f"{name}: member {member.name!r} is not in the manifest "
                                        f"(the manifest lists {len(expected_keys)} records)")
                    if key != expected_keys[position]:
                        raise DataError(f"{name}: member {position} is {key!r}, the manifest expects "
                                        f"{expected_keys[position]!r}")
                extracted = tar.extractfile(member)
                payload = extracted.read() if extracted is not None else b""
                if len(payload) != member.size:
                    raise DataError(f"{name} record {key}: truncated shard ({len(payload)} of {member.size} bytes)")
                position += 1
                yield key, payload
    except (tarfile.TarError, EOFError, OSError) as e:
        last = f" after {position} records" if position else ""
        raise DataError(f"{name}: truncated or corrupt tar{last}: {_one_line(e)}") from None
    if expected_keys is not None and position != len(expected_keys):
        raise DataError(f"{name}: truncated shard: {position} of {len(expected_keys)} records "
                        f"(first missing: {expected_keys[position]})")


def _member_key(member: tarfile.TarInfo, shard: str) -> str:
    if not member.isfile() or not member.name.endswith(".npz"):
        raise DataError(f"{shard}: unexpected member {member.name!r} (expected <key>.npz files)")
    key = member.name[: -len(".npz")]
    if not _KEY_RE.match(key):
        raise DataError(f"{shard}: bad record key {key!r} in member {member.name!r}")
    return key


class ShardDataset:
    """A dataset directory read without Ray: `len(ds)`, `ds[i]`, `for rec in ds`, `ds.verify()`.

    Opening checks the manifest and that every shard exists with the size the manifest gives (cheap);
    `verify=True` also runs `verify()` (sha256 of every shard and a full decode of every record).
    Random access builds, once per shard on first use, an index of member offsets by reading the tar
    headers. Records come back validated (dict of numpy arrays, see core.data.record). The object holds
    no open files, so it pickles to worker processes.
    """

    def __init__(self, root: str | os.PathLike, *, verify: bool = False) -> None:
        self.root = Path(root)
        self.manifest = load_manifest(self.root)
        self._shards: list[dict] = self.manifest["shards"]
        self._starts = np.cumsum([0] + [s["num_records"] for s in self._shards])  # len(shards)+1
        self._offsets: dict[int, list[tuple[int, int]]] = {}
        for entry in self._shards:
            path = self.root / entry["filename"]
            if not path.is_file():
                raise DataError(f"missing shard {entry['filename']} (listed in {self.root / MANIFEST_NAME})")
            size = path.stat().st_size
            if size != entry["bytes"]:
                raise DataError(f"{entry['filename']}: size {size} bytes differs from the manifest's "
                                f"{entry['bytes']} (truncated or changed shard)")
        if verify:
            self.verify()

    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def shard_paths(self) -> list[Path]:
        return [self.root / s["filename"] for s in self._shards]

    def _locate(self, index: int) -> tuple[int, int]:
        n = len(self)
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"dataset index must be an int, got {type(index).__name__}")
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError(f"record index {index} out of range for a dataset of {n} records")
        shard = int(np.searchsorted(self._starts, index, side="right") - 1)
        return shard, int(index - self._starts[shard])

    def key(self, index: int) -> str:
        """Record key of record `index`."""
        shard, local = self._locate(index)
        return self._shards[shard]["keys"][local]

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        shard, local = self._locate(index)
        entry = self._shards[shard]
        where = f"{entry['filename']} record {entry['keys'][local]}"
        offset, size = self._member_offsets(shard)[local]
        path = self.root / entry["filename"]
        try:
            with open(path, "rb") as f:
                f.seek(offset)
                payload = f.read(size)
        except FileNotFoundError:
            raise DataError(f"missing shard {entry['filename']} ({path})") from None
        if len(payload) != size:
            raise DataError(f"{where}: truncated shard ({len(payload)} of {size} bytes)")
        return decode_record(payload, where)

    def _member_offsets(self, shard: int) -> list[tuple[int, int]]:
        """(data offset, size) of each member of shard `shard`, checked against the manifest's keys."""
        if shard in self._offsets:
            return self._offsets[shard]
        entry = self._shards[shard]
        name, path = entry["filename"], self.root / entry["filename"]
        offsets: list[tuple[int, int]] = []
        keys: list[str] = []
        try:
            with tarfile.open(path, mode="r:") as tar:
                for member in tar:
                    keys.append(_member_key(member, name))
                    offsets.append((member.offset_data, member.size))
        except FileNotFoundError:
            raise DataError(f"missing shard {name} ({path})") from None
        except (tarfile.TarError, EOFError, OSError) as e:
            raise DataError(f"{name}: truncated or corrupt tar: {_one_line(e)}") from None
        if keys != entry["keys"]:
            missing = [k for k in entry["keys"] if k not in set(keys)]
            detail = f"missing {missing[0]}" if missing else "members differ in order or number"
            raise DataError(f"{name}: members do not match the manifest ({len(keys)} found, "
                            f"{len(entry['keys'])} listed; {detail})")
        self._offsets[shard] = offsets
        return offsets

    def iter_items(self) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
        """Sequentially stream (key, record) over all shards in manifest order."""
        for entry in self._shards:
            yield from iter_shard(self.root / entry["filename"], name=entry["filename"],
                                  expected_keys=entry["keys"])

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        for _, rec in self.iter_items():
            yield rec

    def verify(self, on_record: Callable[[int, str], None] | None = None) -> dict:
        """Check every shard's sha256 against the manifest and decode + validate every record.

        Returns {"shards": n, "records": n, "bytes": total}; raises DataError naming the first bad
        shard (and record). on_record(count_checked, key) reports progress.
        """
        count = 0
        total_bytes = 0
        for entry in self._shards:
            path = self.root / entry["filename"]
            if not path.is_file():
                raise DataError(f"missing shard {entry['filename']} (listed in {self.root / MANIFEST_NAME})")
            digest = sha256_file(path)
            if digest != entry["sha256"]:
                raise DataError(f"{entry['filename']}: sha256 mismatch (file {digest[:12]}…, manifest "
                                f"{entry['sha256'][:12]}…): the shard is corrupt or was changed")
            for key, _ in iter_shard(path, name=entry["filename"], expected_keys=entry["keys"]):
                count += 1
                if on_record is not None:
                    on_record(count, key)
            total_bytes += entry["bytes"]
        return {"shards": len(self._shards), "records": count, "bytes": total_bytes}
