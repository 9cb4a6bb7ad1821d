"""Egomotion inference over a loaded bundle: two RGB-D rig frames -> `ref0_T_ref1` and `cam0_T_cam1`.

Frames (docs/conventions.md#frames): each frame's views are lifted into that frame's own map frame `ref_t` with the
rig calibration only. `ref_t` is given by `world_T_ref0/1` when the caller knows it (records do); else
it is the camera of view 0 at that time (the inference services' convention), where ref0_T_ref1 is
cam0_T_cam1. `world_T_cam` is used only within one time step (relative rig geometry), never across.
"""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.poses import rig_cam_T_ref
from core.models.egomotion_fine import FineFrame
from core.models.egomotion_inputs import egomotion_fine_frame, egomotion_input_volume


def egomotion_from_volumes(net, vol0: torch.Tensor, vol1: torch.Tensor, cam_T_ref0: torch.Tensor,
                           cam_T_ref1: torch.Tensor, *,
                           features: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None),
                           fine: tuple[FineFrame | None, FineFrame | None] = (None, None),
                           ) -> dict[str, torch.Tensor]:
    """The egomotion module on two input volumes B×4×Z×Y×X (each instant in its own ref_t), with
    cam_T_ref0/1 B×V×4×4 -> `ref0_T_ref1` B×4×4 and `cam0_T_cam1` B×4×4 (view 0's camera), and
    `ref0_T_ref1_learned` B×4×4, where the module's learned stages end (before its weightless fine stage). `features`:
    the module's encodings of vol0/vol1 (EgomotionNet.encode) when a stream kept them; None = encode here.
    `fine`: the frames' FineFrames (egomotion_fine_frame) for the module's last stage; without
    them the estimate is the sub-voxel stage's."""
    f0, f1 = features
    if f0 is None and f1 is None:
        ref0_T_ref1 = net(vol0, vol1)["ref0_T_ref1"]  # B×4×4
    else:
        f0 = net.encode(vol0) if f0 is None else f0  # B×F'×Z×Y×X
        f1 = net.encode(vol1) if f1 is None else f1
        ref0_T_ref1 = net.align(f0, f1, vol0, vol1)["ref0_T_ref1"]  # B×4×4
    learned = ref0_T_ref1
    ref0_T_ref1 = net.refine_fine(ref0_T_ref1, *fine)  # B×4×4 (as it was without a fine stage or volumes)
    cam0_T_cam1 = cam_T_ref0[:, 0] @ ref0_T_ref1 @ se3.invert(cam_T_ref1[:, 0])
    return {"ref0_T_ref1": ref0_T_ref1, "cam0_T_cam1": cam0_T_cam1, "ref0_T_ref1_learned": learned}


@torch.no_grad()
def estimate_egomotion(bundle, *, rgb0: torch.Tensor, depth0: torch.Tensor, pix_T_cam0: torch.Tensor,
                       world_T_cam0: torch.Tensor, rgb1: torch.Tensor, depth1: torch.Tensor,
                       pix_T_cam1: torch.Tensor, world_T_cam1: torch.Tensor,
                       world_T_ref0: torch.Tensor | None = None,
                       world_T_ref1: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """rgb0/1: B×V×3×H×W in [0,1]; depth0/1: B×V×H×W; pix_T_cam0/1, world_T_cam0/1: B×V×4×4;
    world_T_ref0/1: B×4×4 or None. Returns `ref0_T_ref1` B×4×4 and `cam0_T_cam1` B×4×4 (view 0)."""
    net = bundle.require("egomotion")
    B, V = rgb0.shape[:2]
    for name, t in (("world_T_cam0", world_T_cam0), ("world_T_cam1", world_T_cam1)):
        check_shape(name, t, (B, V, 4, 4))
    cam_T_ref0 = rig_cam_T_ref(world_T_cam0, world_T_ref0)  # B×V×4×4
    cam_T_ref1 = rig_cam_T_ref(world_T_cam1, world_T_ref1)
    vol0 = egomotion_input_volume(net, rgb0, depth0, pix_T_cam0, cam_T_ref0)  # B×4×Z×Y×X
    vol1 = egomotion_input_volume(net, rgb1, depth1, pix_T_cam1, cam_T_ref1)
    fine = (egomotion_fine_frame(net, depth0, pix_T_cam0, cam_T_ref0),  # FineFrame (parts built on use) or None
            egomotion_fine_frame(net, depth1, pix_T_cam1, cam_T_ref1))
    return egomotion_from_volumes(net, vol0, vol1, cam_T_ref0, cam_T_ref1, fine=fine)
