"""The training job's default learning rate: flow takes the preset's flow_lr (paper: 1e-4), others lr."""

from core.presets import get_preset
from services.training.config import TrainJobConfig, resolve_defaults


def test_flow_defaults_to_flow_lr_and_an_explicit_lr_wins(tmp_path):
    tiny = get_preset("tiny").train
    assert tiny.flow_lr != tiny.lr  # otherwise the test could not tell them apart
    for task, expected in (("flow", tiny.flow_lr), ("egomotion", tiny.lr), ("occupancy", tiny.lr)):
        cfg = resolve_defaults(TrainJobConfig(task=task, data_dir=str(tmp_path), run_dir=str(tmp_path)))
        assert cfg.lr == expected, task
    explicit = resolve_defaults(TrainJobConfig(task="flow", data_dir=str(tmp_path), run_dir=str(tmp_path), lr=3e-3))
    assert explicit.lr == 3e-3
