"""Random view subsets for training (core.tasks.view_subset) against slicing written out view by view."""

import pytest
import torch

from core.tasks.view_subset import random_view_subset


def tiny_batch(B=2, T=2, V=4, H=3, W=5):
    """Every entry names its view: value = view index, so a subset's views can be read back."""
    views = torch.arange(V, dtype=torch.float32)
    return {
        "rgb": views.view(1, 1, V, 1, 1, 1).expand(B, T, V, 3, H, W).clone(),
        "depth": views.view(1, 1, V, 1, 1).expand(B, T, V, H, W).clone(),
        "world_T_cam": views.view(1, 1, V, 1, 1).expand(B, T, V, 4, 4).clone(),
        "pix_T_cam": views.view(1, V, 1, 1).expand(B, V, 4, 4).clone(),
        "world_T_ref": torch.randn(B, T, 4, 4),
    }


def test_every_view_keyed_tensor_keeps_the_same_views_in_order():
    batch = tiny_batch()
    generator = torch.Generator().manual_seed(0)
    sizes = set()
    for _ in range(60):
        out = random_view_subset(batch, min_views=1, generator=generator)
        kept = [int(v) for v in out["pix_T_cam"][0, :, 0, 0]]
        sizes.add(len(kept))
        assert kept == sorted(set(kept)) and 1 <= len(kept) <= 4
        # slow, obvious: pick the same views one by one from the full batch
        for key, axis in (("rgb", 2), ("depth", 2), ("world_T_cam", 2), ("pix_T_cam", 1)):
            expected = torch.stack([batch[key].select(axis, v) for v in kept], dim=axis)
            assert torch.equal(out[key], expected), key
        assert out["world_T_ref"] is batch["world_T_ref"]
    assert sizes == {1, 2, 3, 4}  # every subset size from min_views to V is drawn


def test_min_views_at_or_above_v_keeps_every_view_and_zero_is_refused():
    batch = tiny_batch(V=2)
    assert random_view_subset(batch, min_views=2, generator=None) is batch
    assert random_view_subset(batch, min_views=5, generator=None) is batch
    with pytest.raises(ValueError, match="min_views"):
        random_view_subset(batch, min_views=0, generator=None)
