"""Small tensors run fastest on one thread; a shared 2-core machine thrashes with more."""

import pytest
import torch

from core.geometry import se3
from core.geometry.camera import intrinsics_from_fov


@pytest.fixture(autouse=True)
def _one_torch_thread(one_torch_thread):
    """Every test here runs on one torch thread (tests/conftest.py)."""


def _views(B, V, H, W, grid=None):
    """Cameras at the ref origin turned by yaw, looking at a ground plane 2 m below (Y down)."""
    K = intrinsics_from_fov(H, W, 90.0)[0]
    v = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    yn = (v - K[1, 2]) / K[1, 1]
    depth = torch.where(yn > 0.05, 2.0 / yn.clamp(min=1e-3), torch.full_like(yn, 6.0)).clamp(max=6.0)
    ref_T_cam = torch.zeros(B, V, 4, 4)
    ref_T_cam[..., :, :] = torch.eye(4)
    yaw = torch.linspace(0, 3.0, V)
    ref_T_cam[..., :3, :3] = se3.yaw_to_matrix(yaw)
    return (torch.rand(B, V, 3, H, W), depth.expand(B, V, H, W).clone(), K.expand(B, V, 4, 4).clone(),
            se3.invert(ref_T_cam))


@pytest.fixture
def make_views():
    """make_views(B, V, H, W) -> (rgb, depth, pix_T_cam, cam_T_ref) of a yawing rig over a ground plane."""
    return _views
