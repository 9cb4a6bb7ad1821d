"""The encoder's inference tail in channels-last layout (core.models.encoder3d, "Layout").

Without gradients the upsample and normalisation run on a channels-last copy; the reference is the same
encoder with gradients on, which keeps PyTorch's channels-first layout throughout.
"""

import pytest
import torch

from core.models.encoder3d import Encoder3D


@pytest.mark.parametrize("full_res", [0, 3])
@pytest.mark.parametrize("zyx", [(8, 8, 16), (7, 5, 9)])
def test_inference_features_equal_the_channels_first_path(zyx, full_res):
    torch.manual_seed(0)
    enc = Encoder3D(in_channels=4, width=4, out_channels=6, full_res=full_res).eval()
    volume = torch.randn(2, 4, *zyx)
    reference = enc(volume)  # parameters require grad: the channels-first tail
    assert reference.is_contiguous()
    with torch.no_grad():
        fast = enc(volume)
    assert fast.shape == reference.shape == (2, 6, *zyx)
    torch.testing.assert_close(fast, reference.detach(), rtol=0, atol=1e-6)
    assert torch.allclose(fast.norm(dim=1), torch.ones(2, *zyx), atol=1e-5)


def test_inference_features_come_back_channels_last_and_reshape_like_any_tensor():
    enc = Encoder3D(in_channels=4, width=4, out_channels=6).eval()
    with torch.no_grad():
        fast = enc(torch.randn(2, 4, 8, 8, 16))
    assert fast.is_contiguous(memory_format=torch.channels_last_3d)
    # The mapper splits the batch into B×V: the split must not reorder voxels.
    assert torch.equal(fast.reshape(1, 2, 6, 8, 8, 16)[0, 1], fast[1])


def test_frozen_encoder_under_grad_mode_also_takes_the_fast_tail():
    """A frozen mapper (detector, flow over maps) runs with grad mode on but no parameter needs a gradient."""
    enc = Encoder3D(in_channels=4, width=4, out_channels=6).eval().requires_grad_(False)
    assert enc(torch.randn(1, 4, 8, 8, 8)).is_contiguous(memory_format=torch.channels_last_3d)
