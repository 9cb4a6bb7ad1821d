"""l2_normalize_channels against torch's F.normalize (the obvious reference): values and gradients,
zero vectors included."""

import torch
import torch.nn.functional as F

from core.models.normalize import l2_normalize_channels


def test_matches_f_normalize_values_and_gradients():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 3, 2, 4, generator=g, dtype=torch.float64)
    x[0, :, 1, 1, 1] = 0.0  # a zero vector: both give zeros, not NaN
    a, b = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    fast, slow = l2_normalize_channels(a), F.normalize(b, dim=1)
    torch.testing.assert_close(fast, slow)
    assert torch.isfinite(fast).all() and not fast[0, :, 1, 1, 1].any()
    w = torch.randn(fast.shape, generator=g, dtype=torch.float64)
    (fast * w).sum().backward()
    (slow * w).sum().backward()
    torch.testing.assert_close(a.grad, b.grad)


def test_unit_norm_along_channels_only():
    x = torch.randn(1, 3, 4, 5)
    n = l2_normalize_channels(x).square().sum(1)  # 1×4×5
    torch.testing.assert_close(n, torch.ones_like(n))
