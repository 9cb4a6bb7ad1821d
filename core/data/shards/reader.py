"""Reading records back: one shard as a stream (`iter_shard`, `iter_tar_members`) and a whole dataset
directory with random access (`ShardDataset`). Anything wrong raises DataError naming the shard and record."""

from __future__ import annotations

import io
import os
import tarfile
from pathlib import Path
from typing import BinaryIO, Callable, Iterator, Sequence

import numpy as np

from core.data.shards.codec import decode_record
from core.data.shards.layout import MANIFEST_NAME, RECORD_KEY_RE, one_line
from core.data.shards.manifest import load_manifest, sha256_file
from core.errors import DataError


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
        raise DataError(f"{name}: truncated or corrupt tar{last}: {one_line(e)}") from None
    if expected_keys is not None and position != len(expected_keys):
        raise DataError(f"{name}: truncated shard: {position} of {len(expected_keys)} records "
                        f"(first missing: {expected_keys[position]})")


def _member_key(member: tarfile.TarInfo, shard: str) -> str:
    if not member.isfile() or not member.name.endswith(".npz"):
        raise DataError(f"{shard}: unexpected member {member.name!r} (expected <key>.npz files)")
    key = member.name[: -len(".npz")]
    if not RECORD_KEY_RE.match(key):
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
            raise DataError(f"{name}: truncated or corrupt tar: {one_line(e)}") from None
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
