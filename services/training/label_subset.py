"""A detector run's label budget: RUN_DIR/labelled_data, a copy of the first N records of a dataset
(or of records [first, first + N): the paper benchmark's further label draws).

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


def labelled_subset(data_dir: Path, run_dir: Path, count: int, *, first: int = 0,
                    log: Callable[[str], None] = lambda line: None) -> Path:
    """RUN_DIR/labelled_data: records [first, first + count) of `data_dir` (written once; a rerun reuses it
    and refuses another subset, since the run's checkpoints were trained on that one). `log` gets a line
    when the subset is written or `count` exceeds the dataset."""
    from core.data.shards import ShardDataset, load_manifest, write_dataset

    if count < 1:
        raise ConfigError("train detector: --labels must be at least 1 (a detector needs labelled records)")
    if not data_dir.is_dir():
        raise DataError(f"--data {data_dir}: no such dataset directory")
    out = run_dir / LABELLED_SUBDIR
    source = ShardDataset(data_dir)
    if first < 0 or (first > 0 and first + count > len(source)):
        raise ConfigError(f"train detector: records [{first}, {first + count}) are not all in {data_dir}, "
                          f"which has {len(source)}")
    wanted = min(count, len(source))
    if (out / "manifest.json").is_file():
        generator = load_manifest(out).get("generator") or {}
        have = (generator.get("label_subset_of"), generator.get("label_records"), generator.get("label_first", 0))
        if have != (str(data_dir.resolve()), wanted, first):
            raise ConfigError(f"train detector: run dir {run_dir} was trained on {have[1]} records from record "
                              f"{have[2]} of {have[0]}; use a new --run-dir for --labels {count} of {data_dir}")
        return out
    if count > len(source):
        log(f"detector: --labels {count} exceeds the dataset's {len(source)} records; using all of them")
    manifest = source.manifest
    generator = dict(manifest.get("generator") or {}, label_subset_of=str(data_dir.resolve()),
                     label_records=wanted, label_first=first)
    records = ({**source[i], KEY_FIELD: source.key(i)} for i in range(first, first + wanted))
    write_dataset(out, records, split=manifest.get("split", "train"), preset_name=manifest.get("preset"),
                  grid=manifest.get("grid"), generator=generator, seed=manifest.get("seed"), overwrite=True)
    log(f"detector: box labels from records {first}..{first + wanted - 1} of {data_dir} ({out})")
    return out
