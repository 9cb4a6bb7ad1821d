"""The fused upsample + normalise against the two plain ops it replaces (core.models.upsample_normalize)."""

import pytest
import torch
import torch.nn.functional as F

from core.models.normalize import l2_normalize_channels
from core.models.upsample_normalize import upsample_normalize


def reference(features: torch.Tensor, size, eps: float = 1e-12) -> torch.Tensor:
    """Slow, obvious: PyTorch's trilinear upsample, then x / max(‖x‖, eps), autograd through both."""
    return l2_normalize_channels(F.interpolate(features, size=size, mode="trilinear", align_corners=False), eps)


@pytest.mark.parametrize("shape,size", [((2, 5, 3, 2, 4), (6, 4, 8)), ((1, 3, 4, 1, 3), (8, 2, 6)),
                                        ((1, 4, 2, 3, 2), (5, 3, 7))])
def test_values_and_gradients_match_the_plain_ops(shape, size):
    torch.manual_seed(0)
    x = torch.randn(*shape, dtype=torch.float64)
    grad = torch.randn(shape[0], shape[1], *size, dtype=torch.float64)
    fast_in, ref_in = x.clone().requires_grad_(), x.clone().requires_grad_()
    fast, ref = upsample_normalize(fast_in.float(), size), reference(ref_in, size)
    assert fast.dtype == torch.float32 and fast.shape == ref.shape
    assert fast.is_contiguous(memory_format=torch.channels_last_3d)
    torch.testing.assert_close(fast.double(), ref, rtol=0, atol=1e-6)
    fast.backward(grad.float())
    ref.backward(grad)
    torch.testing.assert_close(fast_in.grad, ref_in.grad, rtol=1e-5, atol=1e-5)


def test_backward_formula_by_finite_differences():
    x = torch.randn(1, 3, 2, 3, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: upsample_normalize(t, (4, 5, 4)), (x,))


def test_all_but_zero_features_take_the_clamped_gradient():
    """Below eps the clamp holds the scale constant: gradient = upsampleᵀ(g / eps), as the plain ops give."""
    eps = 1e-3
    x = torch.full((1, 2, 2, 2, 2), 1e-6, dtype=torch.float64)
    x[..., 1] = 1.0  # half the voxels far above eps, half far below
    grad = torch.randn(1, 2, 4, 4, 4, dtype=torch.float64)
    fast_in, ref_in = x.clone().requires_grad_(), x.clone().requires_grad_()
    upsample_normalize(fast_in, (4, 4, 4), eps).backward(grad.float())
    reference(ref_in, (4, 4, 4), eps).backward(grad)
    torch.testing.assert_close(fast_in.grad, ref_in.grad, rtol=1e-5, atol=1e-4)


def test_bf16_input_gives_float32_features_and_a_bf16_gradient():
    x = torch.randn(1, 4, 2, 2, 2).bfloat16().requires_grad_()
    y = upsample_normalize(x, (4, 4, 4))
    assert y.dtype == torch.float32
    y.sum().backward()
    assert x.grad.dtype == torch.bfloat16


def test_wrong_rank_names_the_shape():
    with pytest.raises(ValueError, match="B×F×z×y×x"):
        upsample_normalize(torch.zeros(1, 4, 2, 2), (4, 4, 4))
