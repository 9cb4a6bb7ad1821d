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


def test_autocast_runs_the_convolution_in_bfloat16_like_torch():
    """Under CPU autocast the conv goes through F.conv3d (autocast does not cover torch.mkldnn_convolution,
    which kept convs in float32): bf16 out, equal to nn.Conv3d under the same autocast."""
    torch.manual_seed(0)
    fast = Conv3d(5, 6, 3, padding=1)
    slow = nn.Conv3d(5, 6, 3, padding=1)
    slow.load_state_dict(fast.state_dict())
    x = torch.randn(1, 5, 6, 4, 6)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        ya, yb = fast(x), slow(x)
    assert ya.dtype == torch.bfloat16
    torch.testing.assert_close(ya, yb)
    torch.testing.assert_close(ya.float(), fast(x), rtol=0.05, atol=0.05)   # bf16 keeps ~3 significant digits


def test_torch_compile_traces_the_module():
    """torch.compile could not trace torch.mkldnn_convolution ("itensor_view_from_dense expects CPU tensor
    input"); the module now traces (aot_eager: the graph capture and autograd, without a C++ build)."""
    torch.manual_seed(0)
    conv = Conv3d(5, 6, 3, padding=1)
    x = torch.randn(1, 5, 6, 4, 6, requires_grad=True)
    compiled = torch.compile(conv, backend="aot_eager", fullgraph=True)
    y = compiled(x)
    torch.testing.assert_close(y, nn.functional.conv3d(x, conv.weight, conv.bias, padding=1), rtol=1e-4, atol=1e-4)
    y.sum().backward()
    assert x.grad is not None and conv.weight.grad is not None


@pytest.mark.parametrize("transposed", [False, True])
def test_autocast_keeps_a_one_voxel_thick_strided_conv_in_float32(transposed):
    """oneDNN's CPU bf16 weight gradient breaks for a stride-2 conv whose output (transposed: input) is 1
    voxel high: NaN weight/bias gradients at these channel counts, heap corruption at smaller ones (the
    crash of a tiny bf16 training step; core/models/conv3d.py). Under autocast these convs run in float32,
    so their gradients are finite and match float32 ones; a 2-voxel-high one stays bfloat16."""
    from core.models.conv3d import ConvTranspose3d
    torch.manual_seed(0)
    cls, shape = (ConvTranspose3d, (1, 64, 4, 1, 4)) if transposed else (Conv3d, (1, 64, 8, 2, 8))
    conv = cls(64, 128 if not transposed else 32, 4, stride=2, padding=1)
    x = torch.randn(shape)
    y32 = conv(x)
    w = torch.randn(y32.shape)
    (y32 * w).sum().backward()
    ref = [p.grad.clone() for p in (conv.weight, conv.bias)]
    conv.zero_grad()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = conv(x)
    (y.float() * w).sum().backward()
    for got, want in zip((conv.weight.grad, conv.bias.grad), ref):
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-3)
    assert y.dtype == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16):   # 2 voxels high on the conv side: bf16 as usual
        thicker = conv(torch.randn(shape[0], shape[1], 8, 4, 8) if not transposed else torch.randn(1, 64, 4, 2, 4))
    assert thicker.dtype == torch.bfloat16
