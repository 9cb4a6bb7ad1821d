"""Ray Data over our tar shards: a stream of `(shard, key, npz bytes)` rows, decoded on the workers.

Why rows of raw npz bytes rather than decoded tensor columns: records may differ in box count K
(and Arrow tensor columns want one shape per block), and decoding on the training workers spreads
that cost over them and reuses the one validated decoder (`core.data.shards.decode_record`). The
read tasks only split tar files into members and check them against the manifest with core's
shard readers (`core.data.shards.dataset_shard_paths` and `iter_tar_members`, the checks every other
reader runs), so a missing, truncated or reordered shard fails with a `DataError` naming it. Only the
Ray glue lives here: core never imports Ray.

`TorchTrainer(datasets={"train": ds})` gives each worker a disjoint, equal streaming split; every
epoch re-reads the files in a new order (`shuffle="files"`), and the loop adds a local shuffle buffer.
"""

from __future__ import annotations

import os

import numpy as np

from core.data.shards import dataset_shard_paths, decode_record, iter_tar_members

COLUMNS = ("shard", "key", "npz")
_BLOCK_RECORDS = 32            # rows per block yielded by a read task
_BLOCK_BYTES = 64 << 20        # ...or fewer, once this many payload bytes are buffered


def _make_datasource_class():
    """Defined lazily so importing this module does not import Ray (the CLI stays fast)."""
    import pyarrow as pa
    from ray.data.datasource import FileBasedDatasource

    class TarShardDatasource(FileBasedDatasource):
        """Reads our WebDataset-layout tar shards into blocks of (shard, key, npz) rows."""

        _FILE_EXTENSIONS = ["tar"]

        def __init__(self, paths: list[str], *, keys_by_shard: dict[str, list[str]], **kwargs):
            super().__init__(paths, file_extensions=["tar"], **kwargs)
            self._keys_by_shard = keys_by_shard

        def _read_stream(self, f, path: str):
            name = os.path.basename(path)
            rows: list[tuple[str, bytes]] = []
            buffered = 0
            for key, payload in iter_tar_members(f, name, self._keys_by_shard.get(name)):
                rows.append((key, payload))
                buffered += len(payload)
                if len(rows) >= _BLOCK_RECORDS or buffered >= _BLOCK_BYTES:
                    yield _block(pa, name, rows)
                    rows, buffered = [], 0
            if rows:
                yield _block(pa, name, rows)

    return TarShardDatasource


def _block(pa, name: str, rows: list[tuple[str, bytes]]):
    return pa.table({
        "shard": pa.array([name] * len(rows), type=pa.string()),
        "key": pa.array([k for k, _ in rows], type=pa.string()),
        "npz": pa.array([p for _, p in rows], type=pa.large_binary()),
    })


def read_shards(data_dir: str | os.PathLike, *, seed: int):
    """A Ray Dataset streaming the records of `data_dir` as (shard, key, npz) rows.

    Files are shuffled each epoch (seeded, reseeded per execution). Call inside a Ray session.
    """
    import ray.data
    from ray.data import FileShuffleConfig

    paths, keys, _ = dataset_shard_paths(data_dir)
    datasource = _make_datasource_class()(
        paths, keys_by_shard=keys,
        shuffle=FileShuffleConfig(seed=seed, reseed_after_execution=True))
    return ray.data.read_datasource(datasource)


def decode_rows(batch: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
    """A numpy batch of (shard, key, npz) rows → list of validated records."""
    return [decode_record(bytes(payload), f"{shard} record {key}")
            for shard, key, payload in zip(batch["shard"], batch["key"], batch["npz"])]
