"""Shared fixtures of the integration tests: a tiny generated dataset (made once per session)."""

from __future__ import annotations

import pytest

TRAIN_RECORDS = 8


@pytest.fixture(scope="session")
def tiny_train_data(tmp_path_factory):
    """A tiny-preset synthetic dataset directory (8 records, one shard) for training tests."""
    from core.data.shards import write_dataset
    from core.presets import get_preset
    from core.synthetic import generate_record

    preset = get_preset("tiny")
    out = tmp_path_factory.mktemp("tiny_train_data")
    records = (generate_record(preset, seed=1000 + i) for i in range(TRAIN_RECORDS))
    write_dataset(out, records, split="train", preset_name="tiny", grid=preset.grid.to_dict(),
                  generator={"source": "synthetic", "seeds": f"1000..{1000 + TRAIN_RECORDS - 1}"},
                  seed=1000, shard_bytes=2 << 20)  # ~4 records per shard: several files to split
    return out
