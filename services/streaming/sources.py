"""Frame sources for the simulated camera: a dataset on disk or the live synthetic world.

A source yields plain frames (one camera view at one time step) as dicts:
    rgb H×W×3 uint8, depth H×W float32 (metres, 0 = missing), pix_T_cam 4×4, world_T_cam 4×4,
    scene_start (bool: the first frame of a record).
Records are walked in time order, one view (`view`) of each; consecutive records are separate
episodes, so the stream "cuts" between them like a camera moved to a new place, and says so
(`scene_start`, the Frame field): a bridge pairs no frame across the cut (a pair across it once gave a
5 m "moving object" at 5.4 m/s in the quick start).
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from core.errors import ConfigError


def frames_from_records(records, *, view: int = 0) -> Iterator[dict]:
    """Yield the frames of `view` of every record, in time order. Shapes as in the module doc."""
    for record in records:
        T, V = record["rgb"].shape[:2]
        if not 0 <= view < V:
            raise ConfigError(f"--view {view} out of range: the records have {V} views")
        for t in range(T):
            yield {
                "rgb": np.ascontiguousarray(record["rgb"][t, view]),            # H×W×3
                "depth": np.ascontiguousarray(record["depth"][t, view]),        # H×W
                "pix_T_cam": np.asarray(record["pix_T_cam"][view], np.float32),  # 4×4
                "world_T_cam": np.asarray(record["world_T_cam"][t, view], np.float32),  # 4×4
                "scene_start": t == 0,
            }


def dataset_frames(root: str, *, view: int = 0, loop: bool = False) -> Iterator[dict]:
    """Frames of a shard dataset directory (see core.data.shards). The dataset is opened and `view`
    checked against the manifest's view counts now, so a bad path or view fails before the camera starts."""
    from core.data.shards import ShardDataset

    dataset = ShardDataset(root)
    views = (dataset.manifest.get("dims") or {}).get("V")  # [min, max] over the records
    if views and not 0 <= view < views[0]:
        raise ConfigError(f"--view {view} out of range: the records of {root} have {views[0]} views")
    return _dataset_frames(dataset, view=view, loop=loop)


def _dataset_frames(dataset, *, view: int, loop: bool) -> Iterator[dict]:
    while True:
        yield from frames_from_records(dataset, view=view)
        if not loop:
            return


def synthetic_frames(*, preset_name: str, seed: int, frames_per_episode: int = 8,
                     moving_ego: bool = False) -> Iterator[dict]:
    """An endless stream from the synthetic world: episode after episode of `frames_per_episode`
    steps, each a fresh scene (seed, seed+1, ...) with moving vehicles."""
    from core.presets import get_preset
    from core.synthetic import generate_record

    preset = get_preset(preset_name)
    episode = 0
    while True:
        record = generate_record(preset, seed=seed + episode, num_views=1, num_frames=frames_per_episode,
                                 moving_ego=moving_ego)
        yield from frames_from_records([record], view=0)
        episode += 1
