"""`serve` / `stream bridge --no-egomotion-fine`: the flag reaches the runtime, and a runtime built with it
serves the bundle's egomotion module without its fine stage (core/models/egomotion_fine.py)."""

import pytest
import torch

from core.bundle import save_bundle
from core.models.egomotion import EgomotionNet
from core.presets import get_preset
from services.cli.main import build_parser
from services.inference.runtime import _load


@pytest.fixture
def bundle_dir(tmp_path):
    preset = get_preset("tiny")
    net = EgomotionNet(grid=preset.grid, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8,
                       input_occupancy="splat", refine={"levels": [[1.0, 0.1, 1]]})
    return save_bundle(tmp_path / "b", modules={"egomotion": net}, preset=preset, provenance={"task": "egomotion"},
                       metrics={})


def test_a_runtime_loads_the_fine_stage_unless_told_not_to(bundle_dir):
    with_fine = _load(str(bundle_dir), torch.device("cpu")).bundle.modules["egomotion"]
    without = _load(str(bundle_dir), torch.device("cpu"), egomotion_fine=False).bundle.modules["egomotion"]
    assert with_fine.fine is not None and with_fine.fine_grid is not None
    assert without.fine is None and without.fine_grid is None
    E = torch.eye(4)[None]
    vol = torch.rand(1, 1, *get_preset("tiny").grid.scaled(0.5).shape_zyx)  # any volume: the stage is off
    assert without.refine_fine(E, vol, vol) is E


@pytest.mark.parametrize("argv", [["serve", "--bundle", "B"], ["stream", "bridge", "--bundle", "B"]])
def test_the_flag_parses_for_serve_and_the_bridge(argv):
    parser = build_parser(argv)
    assert parser.parse_args(argv).egomotion_fine is True
    assert parser.parse_args([*argv, "--no-egomotion-fine"]).egomotion_fine is False
