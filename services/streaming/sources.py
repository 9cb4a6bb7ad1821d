"""Frame sources for the simulated camera: a dataset on disk or the live synthetic world.

A source yields plain frames (one camera view at one time step) as dicts:
    rgb H×W×3 uint8, depth H×W float32 (metres, 0 = missing), pix_T_cam 4×4, world_T_cam 4×4,
    scene_start (bool: the first frame of a record), capture_offset (seconds on the source's capture
    clock since its first frame, or None when the source does not know when its frames were captured).
A replay publishes at its own rate, but the world in it moved in capture time: the camera stamps each
frame's capture time from capture_offset, so velocities come out in world terms at any replay rate.
Records are walked in time order, one view (`view`) of each; consecutive records are separate
episodes, so the stream "cuts" between them like a camera moved to a new place, and says so
(`scene_start`, the Frame field): a bridge pairs no frame across the cut (a pair across it once gave a
5 m "moving object" at 5.4 m/s in the quick start).
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from core.errors import ConfigError


def frames_from_records(records, *, view: int = 0, capture_dt: float | None = None) -> Iterator[dict]:
    """Yield the frames of `view` of every record, in time order. Shapes as in the module doc.
    `capture_dt`: seconds between consecutive frames when captured (None: unknown); the capture clock runs
    on across records (a cut is marked by scene_start, not by a jump of the clock)."""
    if capture_dt is not None and not capture_dt > 0:
        raise ConfigError(f"--capture-dt must be positive seconds, got {capture_dt}")
    index = 0
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
                "capture_offset": None if capture_dt is None else index * capture_dt,
            }
            index += 1


def dataset_frames(root: str, *, view: int = 0, loop: bool = False, capture_dt: float | None = None) -> Iterator[dict]:
    """Frames of a shard dataset directory (see core.data.shards). The dataset is opened and `view`
    checked against the manifest's view counts now, so a bad path or view fails before the camera starts.
    `capture_dt`: seconds between a record's frames when captured; None: the synthetic world's step for a
    dataset `n3dmap data generate` wrote, else unknown (records keep no capture times)."""
    from core.data.shards import ShardDataset

    dataset = ShardDataset(root)
    views = (dataset.manifest.get("dims") or {}).get("V")  # [min, max] over the records
    if views and not 0 <= view < views[0]:
        raise ConfigError(f"--view {view} out of range: the records of {root} have {views[0]} views")
    if capture_dt is None:
        capture_dt = synthetic_step(dataset.manifest)
    return _dataset_frames(dataset, view=view, loop=loop, capture_dt=capture_dt)


def synthetic_step(manifest: dict) -> float | None:
    """Seconds between the frames of a synthetic dataset (its world's `dt`, as the generator recorded it,
    else the preset's); None for any other source."""
    generator = manifest.get("generator") or {}
    if generator.get("source") != "synthetic":
        return None
    from core.presets import get_preset
    from core.synthetic.config import world_with

    try:
        return float(world_with(get_preset(manifest["preset"]), generator.get("world") or {}).dt)
    except (KeyError, ValueError) as e:   # a manifest this build cannot read the world of
        raise ConfigError(f"the dataset's manifest names no synthetic world this build knows ({e}); give "
                          "--capture-dt S, the seconds between its frames") from e


def _dataset_frames(dataset, *, view: int, loop: bool, capture_dt: float | None) -> Iterator[dict]:
    def passes():
        while True:
            yield from dataset
            if not loop:
                return
    # one capture clock over every pass, so a looped replay's clock keeps advancing
    yield from frames_from_records(passes(), view=view, capture_dt=capture_dt)


def synthetic_frames(*, preset_name: str, seed: int, frames_per_episode: int = 8,
                     moving_ego: bool = False) -> Iterator[dict]:
    """An endless stream from the synthetic world: episode after episode of `frames_per_episode`
    steps, each a fresh scene (seed, seed+1, ...) with moving vehicles."""
    from core.presets import get_preset
    from core.synthetic import generate_record

    from core.synthetic.config import world_with

    preset = get_preset(preset_name)

    def records():
        episode = 0
        while True:
            yield generate_record(preset, seed=seed + episode, num_views=1, num_frames=frames_per_episode,
                                  moving_ego=moving_ego)
            episode += 1
    yield from frames_from_records(records(), view=0, capture_dt=world_with(preset, {}).dt)
