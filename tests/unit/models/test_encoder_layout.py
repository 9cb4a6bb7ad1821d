"""The encoder's tail (core.models.encoder3d, "Tail"): fused upsample + normalise in channels-last layout on
CPU, against the encoder written out with the two plain channels-first ops."""

import pytest
import torch
import torch.nn.functional as F

from core.models.encoder3d import Encoder3D
from core.models.normalize import l2_normalize_channels


def plain_forward(enc: Encoder3D, volume: torch.Tensor) -> torch.Tensor:
    """Slow, obvious reference: the same layers, PyTorch's upsample and the normalisation, channels-first."""
    Z, Y, X = volume.shape[-3:]
    x0 = F.pad(volume, (0, (-X) % 8, 0, (-Y) % 8, 0, (-Z) % 8))
    x1 = enc.down1(x0)
    x2 = enc.down2(x1)
    u1 = torch.cat([enc.up1(enc.down3(x2)), x2], dim=1)
    feat = enc.out(torch.cat([enc.up2(u1), x1], dim=1)).contiguous()
    feat = F.interpolate(feat, size=x0.shape[-3:], mode="trilinear", align_corners=False)[..., :Z, :Y, :X]
    if enc.full_res > 0:
        feat = enc.fuse0(torch.cat([feat, enc.skip0(volume)], dim=1))
    return l2_normalize_channels(feat) if enc.normalize else feat


@pytest.mark.parametrize("full_res", [0, 3])
@pytest.mark.parametrize("zyx", [(8, 8, 16), (7, 5, 9)])
def test_features_and_weight_gradients_equal_the_plain_tail(zyx, full_res):
    torch.manual_seed(0)
    enc = Encoder3D(in_channels=4, width=4, out_channels=6, full_res=full_res).eval()
    volume = torch.randn(2, 4, *zyx)
    grad = torch.randn(2, 6, *zyx)
    reference = plain_forward(enc, volume)
    reference.backward(grad)
    ref_grads = [p.grad.clone() for p in enc.parameters()]
    enc.zero_grad()
    fast = enc(volume)
    fast.backward(grad)
    assert fast.shape == reference.shape == (2, 6, *zyx)
    torch.testing.assert_close(fast, reference, rtol=0, atol=1e-6)
    for p, ref_grad in zip(enc.parameters(), ref_grads):
        torch.testing.assert_close(p.grad, ref_grad, rtol=1e-4, atol=1e-5)
    with torch.no_grad():
        torch.testing.assert_close(enc(volume), reference.detach(), rtol=0, atol=1e-6)


def test_features_come_back_channels_last_and_reshape_like_any_tensor():
    enc = Encoder3D(in_channels=4, width=4, out_channels=6).eval()
    with torch.no_grad():
        fast = enc(torch.randn(2, 4, 8, 8, 16))
    assert fast.is_contiguous(memory_format=torch.channels_last_3d)
    # The mapper splits the batch into B×V: the split must not reorder voxels.
    assert torch.equal(fast.reshape(1, 2, 6, 8, 8, 16)[0, 1], fast[1])


def test_frozen_full_res_encoder_under_grad_mode_equals_the_plain_tail():
    """A frozen mapper (detector, flow over maps) runs with grad mode on but no parameter needs a gradient."""
    enc = Encoder3D(in_channels=4, width=4, out_channels=6, full_res=2).eval().requires_grad_(False)
    volume = torch.randn(1, 4, 8, 8, 8)
    torch.testing.assert_close(enc(volume), plain_forward(enc, volume), rtol=0, atol=1e-6)
