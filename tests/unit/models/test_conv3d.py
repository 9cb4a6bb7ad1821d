"""core.models.conv3d.Conv3d against torch's nn.Conv3d with the same weights (the reference):
outputs and gradients, batch 1 (where the oneDNN path differs from torch's choice) and 2, strided."""

import pytest
import torch
from torch import nn

from core.models.conv3d import Conv3d


@pytest.mark.parametrize("batch, kernel, stride, padding", [(1, 3, 1, 1), (2, 3, 1, 1), (1, 4, 2, 1), (1, 1, 1, 0)])
def test_matches_nn_conv3d(batch, kernel, stride, padding):
    torch.manual_seed(0)
    fast = Conv3d(5, 6, kernel, stride=stride, padding=padding)
    slow = nn.Conv3d(5, 6, kernel, stride=stride, padding=padding)
    slow.load_state_dict(fast.state_dict())  # same parameters, same state-dict keys
    x = torch.randn(batch, 5, 6, 4, 6)
    xa, xb = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    ya, yb = fast(xa), slow(xb)
    torch.testing.assert_close(ya, yb, rtol=1e-4, atol=1e-4)
    w = torch.randn(ya.shape)
    (ya * w).sum().backward()
    (yb * w).sum().backward()
    torch.testing.assert_close(xa.grad, xb.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(fast.weight.grad, slow.weight.grad, rtol=1e-4, atol=1e-3)


def test_other_dtypes_fall_back_to_torch():
    conv = Conv3d(2, 3, 3, padding=1).double()
    x = torch.randn(1, 2, 4, 4, 4, dtype=torch.float64)
    torch.testing.assert_close(conv(x), nn.functional.conv3d(x, conv.weight, conv.bias, padding=1))
