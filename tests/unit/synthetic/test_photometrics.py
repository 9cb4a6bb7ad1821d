"""Camera photometrics (core/synthetic/photometrics.py) against a per-image reference loop, and their
place in generate_record: off leaves a record untouched, on changes its colours and nothing else."""

import numpy as np
import pytest
import torch

from core.errors import ShapeError
from core.presets import TINY
from core.synthetic import default_world_config, generate_record
from core.synthetic.photometrics import apply_photometrics


def _reference(rgb: torch.Tensor, exposure: float, balance: float, noise: float, seed: int) -> torch.Tensor:
    """The obvious form: draw each image's gains with the same generator calls, then loop over images,
    channels and pixels' noise one image at a time."""
    gen = torch.Generator().manual_seed(seed)
    C = rgb.shape[0]
    e = exposure * torch.randn(C, 1, generator=gen)
    w = balance * torch.randn(C, 3, generator=gen)
    n = torch.randn(rgb.shape, generator=gen) if noise > 0 else torch.zeros(rgb.shape)
    out = torch.empty_like(rgb)
    for c in range(C):
        for k in range(3):
            gain = float(torch.exp(e[c, 0] + w[c, k]))
            out[c, :, :, k] = torch.clamp(rgb[c, :, :, k] * gain + noise * n[c, :, :, k], 0.0, 1.0)
    return out


def test_matches_the_reference():
    rgb = torch.rand(5, 4, 6, 3, generator=torch.Generator().manual_seed(1))  # C×H×W×3
    got = apply_photometrics(rgb, exposure_std=0.3, white_balance_std=0.1, pixel_noise_std=0.05,
                             generator=torch.Generator().manual_seed(9))
    assert torch.allclose(got, _reference(rgb, 0.3, 0.1, 0.05, seed=9), atol=1e-6)
    assert got.min() >= 0 and got.max() <= 1


def test_exposure_alone_scales_each_image_by_one_gain():
    rgb = 0.2 + 0.3 * torch.rand(4, 3, 5, 3, generator=torch.Generator().manual_seed(2))  # stays below 1 at gain ≤ 1.6
    got = apply_photometrics(rgb, exposure_std=0.15, white_balance_std=0.0, pixel_noise_std=0.0,
                             generator=torch.Generator().manual_seed(3))
    ratio = got / rgb                                                     # C×H×W×3
    per_image = ratio.reshape(4, -1)
    assert torch.allclose(per_image, per_image[:, :1].expand_as(per_image), atol=1e-5)  # one gain per image
    assert per_image[:, 0].std() > 0.01                                   # and the images differ


def test_off_returns_the_input_and_draws_nothing():
    rgb = torch.rand(2, 3, 4, 3)
    gen = torch.Generator().manual_seed(4)
    state = gen.get_state()
    assert apply_photometrics(rgb, exposure_std=0.0, white_balance_std=0.0, pixel_noise_std=0.0,
                              generator=gen) is rgb
    assert torch.equal(gen.get_state(), state)


@pytest.mark.parametrize("kwargs, error", [
    ({"exposure_std": -0.1}, ValueError), ({"pixel_noise_std": float("nan")}, ValueError)])
def test_refuses_bad_settings(kwargs, error):
    settings = {"exposure_std": 0.0, "white_balance_std": 0.0, "pixel_noise_std": 0.0, **kwargs}
    with pytest.raises(error, match=next(iter(kwargs))):
        apply_photometrics(torch.rand(1, 2, 2, 3), generator=torch.Generator(), **settings)


def test_refuses_a_wrong_shape():
    with pytest.raises(ShapeError, match="C×H×W×3"):
        apply_photometrics(torch.rand(2, 2, 3), exposure_std=0.1, white_balance_std=0.0, pixel_noise_std=0.0,
                           generator=torch.Generator())


def test_world_config_refuses_negative_settings_and_bad_texture_scales():
    world = default_world_config(TINY)
    with pytest.raises(ValueError, match="white_balance_std"):
        world.with_overrides(white_balance_std=-1.0)
    with pytest.raises(ValueError, match="texture_scale"):
        world.with_overrides(texture_scale=(0.5, 0.2))


def test_generate_record_changes_only_the_colours():
    torch.set_num_threads(1)
    plain = generate_record(TINY, seed=3, num_frames=2)
    world = default_world_config(TINY).with_overrides(exposure_std=0.3, white_balance_std=0.1, pixel_noise_std=0.02)
    camera = generate_record(TINY, seed=3, num_frames=2, world=world)
    for key in plain:
        if key != "rgb":
            assert np.array_equal(plain[key], camera[key]), key
    assert not np.array_equal(plain["rgb"], camera["rgb"])
    # Exposure: the mean brightness ratio differs between the images of one record.
    bright = camera["rgb"].astype(np.float64).mean(axis=(2, 3, 4)) / plain["rgb"].astype(np.float64).mean(axis=(2, 3, 4))
    assert bright.std() > 0.05                                            # T×V image gains spread
    again = generate_record(TINY, seed=3, num_frames=2, world=world)
    assert np.array_equal(camera["rgb"], again["rgb"])                   # still deterministic by seed
