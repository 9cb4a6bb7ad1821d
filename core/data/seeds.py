"""Record seeds of a generated synthetic dataset (a data contract: docs/data.md).

Record i of a dataset generated with seed S is `generate_record(preset, seed=S·SEED_STRIDE + i)`, so a
record can be rebuilt alone, and datasets with different S never share a record as long as each holds
fewer than SEED_STRIDE records. `n3dmap data generate` and the paper benchmark both name records so.
"""

from __future__ import annotations

SEED_STRIDE = 100003


def episode_seed(seed: int, index: int) -> int:
    """Seed of record `index` of a dataset generated with `--seed seed`."""
    return seed * SEED_STRIDE + index
