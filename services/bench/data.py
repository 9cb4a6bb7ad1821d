"""The benchmark's datasets: synthetic train/test sets and the label-budget subsets of the train set.

Records come from `core.synthetic.generate_record` with the seeds of `n3dmap data generate --seed S`
(record i: S·100003 + i), moving ego on every second record ("mixed"), written by
`core.data.shards.write_dataset`. The test set uses seed S + 1, so it shares no record with the
training set; its static-camera and moving-camera halves give the paper's two moving-object settings.

A label budget of N records is a dataset holding the first N training records: the detector's loss
only ever sees labelled records (unlabelled ones contribute exactly nothing to it), so training on
the subset is the same objective as masking the others, with no step spent on records without labels.
"""

from __future__ import annotations

from pathlib import Path

from core.data.shards import ShardDataset, write_dataset
from core.presets import get_preset
from services.cli.data import SEED_STRIDE, episode_seed


def generate_split(out_dir: Path, *, preset: str, episodes: int, seed: int, split: str) -> dict:
    """Write `episodes` synthetic records (moving ego on odd indices) to `out_dir`; returns the manifest."""
    from core.synthetic import generate_record

    p = get_preset(preset)

    def records():
        for i in range(episodes):
            yield generate_record(p, seed=episode_seed(seed, i), moving_ego=i % 2 == 1)

    generator = {"source": "synthetic", "episodes": episodes, "num_views": p.num_views,
                 "num_frames": p.num_frames, "moving_ego": "mixed", "sparse_depth": False, "noise": 0.0,
                 "record_seed": f"seed*{SEED_STRIDE} + index"}
    return write_dataset(out_dir, records(), split=split, preset_name=p.name, grid=p.grid.to_dict(),
                         generator=generator, seed=seed, overwrite=True)


def write_label_subset(train_dir: Path, out_dir: Path, *, count: int) -> dict:
    """The first `count` records of the dataset at `train_dir`, as a dataset at `out_dir`."""
    source = ShardDataset(train_dir)
    manifest = source.manifest
    generator = dict(manifest.get("generator") or {}, label_subset_of=str(train_dir), label_records=count)
    return write_dataset(out_dir, (source[i] for i in range(min(count, len(source)))),
                         split=manifest.get("split", "train"), preset_name=manifest.get("preset"),
                         grid=manifest.get("grid"), generator=generator, seed=manifest.get("seed"),
                         overwrite=True)
