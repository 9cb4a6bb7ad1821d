"""Camera photometric effects: per-image exposure and white balance, and per-pixel sensor noise.

The renderer's colour is albedo × fixed lights, the same from every view (textures.py): every camera of
a record sees a surface in exactly the same colour. Real cameras do not — auto-exposure and auto white
balance change each image's gain, and the sensor adds noise — which makes a view's colours partly
unpredictable from the other views. The paper argues exactly this against colour regression ("unimodal
losses such as mean squared error are not very useful when predicting high dimensional data, due to the
stochasticity of the output space") and for view-contrastive prediction; these effects let the synthetic
world have that stochasticity. All off (0) by default, which leaves records bit for bit as before.

Random draws are made on the CPU from the record's seeded generator and moved to the image's device, so
a seed gives the same images on CPU and CUDA.
"""

from __future__ import annotations

import torch

from core.errors import ShapeError


def apply_photometrics(rgb: torch.Tensor, *, exposure_std: float, white_balance_std: float,
                       pixel_noise_std: float, generator: torch.Generator) -> torch.Tensor:
    """rgb: C×H×W×3 floats in [0, 1] (C camera images) -> C×H×W×3 in [0, 1].

    Image c becomes clamp(rgb_c · exp(e_c) · exp(w_c) + n, 0, 1), with e_c ~ N(0, exposure_std²) one
    log-gain per image, w_c ~ N(0, white_balance_std²) one log-gain per image and channel, and
    n ~ N(0, pixel_noise_std²) per pixel and channel. Returns `rgb` itself when all three are 0 (and then
    draws nothing from `generator`).
    """
    if rgb.dim() != 4 or rgb.shape[-1] != 3:
        raise ShapeError(f"rgb must be C×H×W×3, got {tuple(rgb.shape)}")
    for name, value in (("exposure_std", exposure_std), ("white_balance_std", white_balance_std),
                        ("pixel_noise_std", pixel_noise_std)):
        if not value >= 0:
            raise ValueError(f"{name} must be >= 0, got {value}")
    if exposure_std == 0 and white_balance_std == 0 and pixel_noise_std == 0:
        return rgb
    C = rgb.shape[0]
    log_gain = exposure_std * torch.randn(C, 1, generator=generator)                      # C×1
    log_gain = log_gain + white_balance_std * torch.randn(C, 3, generator=generator)      # C×3
    gain = torch.exp(log_gain).to(rgb.device, rgb.dtype).view(C, 1, 1, 3)                 # C×1×1×3
    out = rgb * gain
    if pixel_noise_std > 0:
        noise = torch.randn(rgb.shape, generator=generator, dtype=torch.float32)          # C×H×W×3
        out = out + pixel_noise_std * noise.to(rgb.device, rgb.dtype)
    return out.clamp(0.0, 1.0)
