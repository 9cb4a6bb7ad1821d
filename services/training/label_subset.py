"""A detector run's label budget: RUN_DIR/labelled_data, a copy of the first N records of a dataset.

The detector has no loss but its box losses, so a record without labels adds nothing to training: a
run with N labelled records trains on a copy of the first N records (same keys, same manifest fields)
rather than spending steps on masked ones. `n3dmap train detector --labels N` and the paper benchmark's
label budgets both train this way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from core.data.shards import KEY_FIELD
from core.errors import ConfigError, DataError

LABELLED_SUBDIR = "labelled_data"


def labelled_subset(data_dir: Path, run_dir: Path, count: int, *,
                    log: Callable[[str], None] = lambda line: None) -> Path:
    """RUN_DIR/labelled_data: the first `count` records of `data_dir` (written once; a rerun reuses it
    and refuses a different count, since the run's checkpoints were trained on that subset). `log`
    gets a line when the subset is written or `count` exceeds the dataset."""
    from core.data.shards import ShardDataset, load_manifest, write_dataset

    if count < 1:
        raise ConfigError("train detector: --labels must be at least 1 (a detector needs labelled records)")
    if not data_dir.is_dir():
        raise DataError(f"--data {data_dir}: no such dataset directory")
    out = run_dir / LABELLED_SUBDIR
    source = ShardDataset(data_dir)
    wanted = min(count, len(source))
    if (out / "manifest.json").is_file():
        generator = load_manifest(out).get("generator") or {}
        have = (generator.get("label_subset_of"), generator.get("label_records"))
        if have != (str(data_dir.resolve()), wanted):
            raise ConfigError(f"train detector: run dir {run_dir} was trained on the first {have[1]} records of "
                              f"{have[0]}; use a new --run-dir for --labels {count} of {data_dir}")
        return out
    if count > len(source):
        log(f"detector: --labels {count} exceeds the dataset's {len(source)} records; using all of them")
    manifest = source.manifest
    generator = dict(manifest.get("generator") or {}, label_subset_of=str(data_dir.resolve()),
                     label_records=wanted)
    records = ({**source[i], KEY_FIELD: source.key(i)} for i in range(wanted))
    write_dataset(out, records, split=manifest.get("split", "train"), preset_name=manifest.get("preset"),
                  grid=manifest.get("grid"), generator=generator, seed=manifest.get("seed"), overwrite=True)
    log(f"detector: box labels from the first {wanted} records of {data_dir} ({out})")
    return out
