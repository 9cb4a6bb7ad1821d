"""The benchmark's datasets: synthetic train/test sets and the label-budget subsets of the train set.

Records come from `core.synthetic.generate_record` with the seeds of `n3dmap data generate --seed S`
(record i: S·100003 + i), moving ego on every second record ("mixed"), written by
`core.data.shards.write_dataset`. The test set uses seed S + 1, so it shares no record with the
training set; its static-camera and moving-camera halves give the paper's two moving-object settings.
"""

from __future__ import annotations

from pathlib import Path

from core.data.shards import write_dataset
from core.presets import get_preset
from core.data.seeds import SEED_STRIDE, episode_seed


def generate_split(out_dir: Path, *, preset: str, episodes: int, seed: int, split: str,
                   world: dict | None = None) -> dict:
    """Write `episodes` synthetic records (moving ego on odd indices) to `out_dir`; returns the manifest.
    `world`: WorldConfig fields changed from the preset's world (lists for tuples, as in JSON)."""
    from core.synthetic import generate_record
    from core.synthetic.config import world_with

    p = get_preset(preset)
    world_config = world_with(p, world or {})

    def records():
        for i in range(episodes):
            yield generate_record(p, seed=episode_seed(seed, i), moving_ego=i % 2 == 1, world=world_config)

    generator = {"source": "synthetic", "episodes": episodes, "num_views": p.num_views,
                 "num_frames": p.num_frames, "moving_ego": "mixed", "sparse_depth": False, "noise": 0.0,
                 "record_seed": f"seed*{SEED_STRIDE} + index"}
    if world:   # as `n3dmap data generate` writes it
        generator["world"] = dict(world)
    return write_dataset(out_dir, records(), split=split, preset_name=p.name, grid=p.grid.to_dict(),
                         generator=generator, seed=seed, overwrite=True)
