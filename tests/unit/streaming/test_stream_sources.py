"""The camera sources' capture clock: offsets in the source's own time, whatever rate a replay runs at."""

import numpy as np
import pytest

from core.errors import ConfigError
from services.streaming.sources import dataset_frames, frames_from_records, synthetic_step


def _record(T: int, V: int = 1) -> dict:
    return {"rgb": np.zeros((T, V, 4, 6, 3), np.uint8), "depth": np.ones((T, V, 4, 6), np.float32),
            "pix_T_cam": np.tile(np.eye(4, dtype=np.float32), (V, 1, 1)),
            "world_T_cam": np.tile(np.eye(4, dtype=np.float32), (T, V, 1, 1))}


def test_the_capture_clock_runs_on_across_records_and_cuts_are_marked_apart():
    frames = list(frames_from_records([_record(2), _record(3)], capture_dt=0.2))
    assert [f["scene_start"] for f in frames] == [True, False, True, False, False]
    np.testing.assert_allclose([f["capture_offset"] for f in frames], [0.0, 0.2, 0.4, 0.6, 0.8])
    assert all(f["capture_offset"] is None for f in frames_from_records([_record(2)]))  # unknown: none claimed
    with pytest.raises(ConfigError, match="--capture-dt"):
        next(frames_from_records([_record(2)], capture_dt=0.0))


def test_a_generated_dataset_replays_in_its_worlds_step(tmp_path):
    """`data generate` records the world (and any change to its step) in the manifest; a replay of the
    dataset, looped, keeps one clock; another source's records carry no step and claim none."""
    from services.bench.data import generate_split

    generate_split(tmp_path / "default", preset="tiny", episodes=1, seed=0, split="val")
    generate_split(tmp_path / "slow", preset="tiny", episodes=1, seed=0, split="val", world={"dt": 0.5})
    default = [f["capture_offset"] for f in dataset_frames(str(tmp_path / "default"))]
    assert len(default) == 2 and default == pytest.approx([0.0, 0.2])        # tiny: 2 frames, the world's 0.2 s
    looped = dataset_frames(str(tmp_path / "slow"), loop=True)
    assert [next(looped)["capture_offset"] for _ in range(5)] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    given = [f["capture_offset"] for f in dataset_frames(str(tmp_path / "slow"), capture_dt=0.1)]
    assert given == pytest.approx([0.0, 0.1])                               # --capture-dt wins
    assert synthetic_step({"preset": "tiny", "generator": {"source": "tum"}}) is None


def test_the_live_synthetic_world_runs_on_its_own_step():
    from core.presets import get_preset
    from core.synthetic.config import default_world_config
    from services.streaming.sources import synthetic_frames

    frames = synthetic_frames(preset_name="tiny", seed=0, frames_per_episode=2)
    offsets = [next(frames)["capture_offset"] for _ in range(3)]   # across an episode's cut too
    step = default_world_config(get_preset("tiny")).dt
    assert offsets == pytest.approx([0.0, step, 2 * step]) and step == pytest.approx(0.2)


def test_a_manifest_whose_world_is_unknown_asks_for_the_step():
    with pytest.raises(ConfigError, match="--capture-dt"):
        synthetic_step({"preset": "tiny", "generator": {"source": "synthetic", "world": {"no_such_field": 1}}})
