"""`serve` / `stream bridge --egomotion-fine module|splat|off`: the option reaches the runtime, and a runtime
built with it serves the bundle's egomotion module with its own last stage, the splat stage, or none
(core/models/egomotion_fine.py)."""

import pytest
import torch

from core.bundle import save_bundle
from core.errors import BundleError
from core.models.egomotion import DEFAULT_FINE_ALIGNMENT, EgomotionNet
from core.models.egomotion_fine import FineAlignment
from core.presets import get_preset
from services.cli.main import build_parser
from services.inference.runtime import RuntimeConfig, _load


@pytest.fixture
def bundle_dir(tmp_path):
    preset = get_preset("tiny")
    net = EgomotionNet(grid=preset.grid, width=4, feature_dim=4, radius=(1, 1, 1), hidden=8,
                       input_occupancy="splat", refine={"levels": [[1.0, 0.1, 1]]})
    return save_bundle(tmp_path / "b", modules={"egomotion": net}, preset=preset, provenance={"task": "egomotion"},
                       metrics={})


def test_a_runtime_loads_the_stage_it_is_told_to(bundle_dir):
    def ego(choice):
        return _load(str(bundle_dir), torch.device("cpu"), egomotion_fine=choice).bundle.modules["egomotion"]
    own, splat, off = ego("module"), ego("splat"), ego("off")
    assert own.fine == FineAlignment(**DEFAULT_FINE_ALIGNMENT) and own.fine.kind == "tsdf"
    assert splat.fine == FineAlignment(kind="splat", factor=2) and splat.fine_grid.shape_zyx == (64, 16, 64)
    assert off.fine is None and off.fine_grid is None
    E = torch.eye(4)[None]
    vol = torch.rand(1, 1, *get_preset("tiny").grid.scaled(0.5).shape_zyx)  # any volume: the stage is off
    assert off.refine_fine(E, vol, vol) is E
    with pytest.raises(BundleError, match="egomotion_fine"):
        RuntimeConfig(bundle_dir=str(bundle_dir), egomotion_fine="tsdf")
    # the option was a boolean until session 25
    assert RuntimeConfig(bundle_dir="b", egomotion_fine=True).egomotion_fine == "module"
    assert RuntimeConfig(bundle_dir="b", egomotion_fine=False).egomotion_fine == "off"


@pytest.mark.parametrize("argv, default", [(["serve", "--bundle", "B"], "splat"),
                                           (["stream", "bridge", "--bundle", "B"], "splat")])
def test_the_option_parses_for_serve_and_the_bridge(argv, default):
    parser = build_parser(argv)
    assert parser.parse_args(argv).egomotion_fine == default
    assert parser.parse_args([*argv, "--no-egomotion-fine"]).egomotion_fine == "off"
    for choice in ("module", "splat", "off"):
        assert parser.parse_args([*argv, "--egomotion-fine", choice]).egomotion_fine == choice
