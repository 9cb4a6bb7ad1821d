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

The package's modules: `layout` (names and rules of the format), `codec` (a record <-> a member's npz bytes),
`writer` (`write_dataset`), `manifest` (`load_manifest`, `dataset_shard_paths`), `reader` (`iter_shard`,
`iter_tar_members`, `ShardDataset`); everything public is importable from `core.data.shards`.
"""

from core.data.shards.codec import decode_record, encode_record
from core.data.shards.layout import (DEFAULT_SHARD_BYTES, FORMAT_NAME, KEY_FIELD, MANIFEST_NAME, SCHEMA_VERSION,
                                     shard_filename)
from core.data.shards.manifest import dataset_shard_paths, load_manifest, sha256_file
from core.data.shards.reader import ShardDataset, iter_shard, iter_tar_members
from core.data.shards.writer import check_output_dir, write_dataset

__all__ = ["DEFAULT_SHARD_BYTES", "FORMAT_NAME", "KEY_FIELD", "MANIFEST_NAME", "SCHEMA_VERSION", "ShardDataset",
           "check_output_dir", "dataset_shard_paths", "decode_record", "encode_record", "iter_shard",
           "iter_tar_members", "load_manifest", "sha256_file", "shard_filename", "write_dataset"]
