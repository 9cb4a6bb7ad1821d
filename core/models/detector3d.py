"""3D object detector on the latent map: a Faster-RCNN-style anchor head (axis-aligned boxes + objectness).

The paper (§3, "3D object detection") adapts Faster R-CNN to 3D and outputs axis-aligned 3D boxes
with objectness confidences; it gives no layer sizes, so ours are:

    map B×F×Z×Y×X ─ conv3 F→C ─ max-pool ×stride ─ conv3 C→C ─┐          (3D neck, BN + LeakyReLU)
    B×C×Zc×Yc×Xc ─ flatten Y into channels ─ B×(C·Yc)×Zc×Xc ─ conv3 → H ─ conv3 H→H ─┐ (bird's-eye view)
        ├─ conv1 H→A      objectness logits per anchor
        └─ conv1 H→6A     Faster-RCNN deltas (dx, dy, dz, dlx, dly, dlz) per anchor (detector_boxes)

Anchors: A car-like axis-aligned sizes at every coarse (z, x) cell, at one height (detector_anchors).
Bird's-eye view because objects stand on the ground: one cell per column keeps the head cheap and
lets the y delta place the box vertically. Conventions (docs/conventions.md#boxes): boxes in `ref`, canonical rows
(x, y, z, lx, ly, lz, yaw) with yaw = 0 on output (axis-aligned, as the paper's detector).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from core.errors import check_shape
from core.geometry.grid import GridConfig
from core.models.detector_anchors import anchor_grid, coarse_shape
from core.models.detector_boxes import aabb_to_boxes, decode_deltas, nms_aabb
from core.models.conv3d import Conv3d

# Axis-aligned bounding boxes of a car (~4.3 m × 1.65 m × 1.9 m) heading along x, along z, and at ±45°.
CAR_ANCHOR_SIZES: tuple[tuple[float, float, float], ...] = ((4.3, 1.65, 1.9), (1.9, 1.65, 4.3), (4.0, 1.65, 4.0))


def _conv3d(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(Conv3d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm3d(c_out),
                         nn.LeakyReLU(0.1))


def _conv2d(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out),
                         nn.LeakyReLU(0.1))


class Detector3D(nn.Module):
    """Latent map B×F×Z×Y×X (frame ref) -> objectness logits B×N and box deltas B×N×6 over N anchors."""

    def __init__(self, *, grid: GridConfig | dict, in_channels: int = 32, width: int = 32,
                 head_width: int = 64, stride: int = 4,
                 anchor_sizes: tuple[tuple[float, float, float], ...] | list = CAR_ANCHOR_SIZES,
                 anchor_y: float = 1.2, prior_probability: float = 0.01) -> None:
        """grid: the map's grid; in_channels: F; width: C of the 3D neck; head_width: H of the BEV head;
        stride: voxels per coarse cell (must divide Z, Y, X); anchor_sizes: A rows (lx, ly, lz) metres;
        anchor_y: anchor centre height in ref (metres, Y down); prior_probability: initial objectness."""
        super().__init__()
        self.grid = grid if isinstance(grid, GridConfig) else GridConfig.from_dict(grid)
        self.in_channels, self.width, self.head_width, self.stride = in_channels, width, head_width, stride
        self.anchor_sizes = tuple(tuple(float(v) for v in s) for s in anchor_sizes)
        self.anchor_y, self.prior_probability = float(anchor_y), float(prior_probability)
        Zc, Yc, Xc = coarse_shape(self.grid, stride)
        A = len(self.anchor_sizes)
        self.num_anchors_per_cell = A

        self.neck3d = nn.Sequential(_conv3d(in_channels, width), nn.MaxPool3d(stride), _conv3d(width, width))
        self.neck2d = nn.Sequential(_conv2d(width * Yc, head_width), _conv2d(head_width, head_width))
        self.objectness = nn.Conv2d(head_width, A, 1)
        self.deltas = nn.Conv2d(head_width, 6 * A, 1)
        # Start from a low objectness everywhere (RetinaNet's prior) so early decoding is quiet;
        # deltas start at zero (boxes = anchors).
        nn.init.constant_(self.objectness.bias, -math.log((1 - prior_probability) / prior_probability))
        nn.init.normal_(self.objectness.weight, std=0.01)
        nn.init.zeros_(self.deltas.weight)
        nn.init.zeros_(self.deltas.bias)
        self.register_buffer("anchors", anchor_grid(self.grid, stride=stride, sizes=self.anchor_sizes,
                                                    y_centre=self.anchor_y), persistent=False)  # N×6

    def config(self) -> dict:
        return {"grid": self.grid.to_dict(), "in_channels": self.in_channels, "width": self.width,
                "head_width": self.head_width, "stride": self.stride,
                "anchor_sizes": [list(s) for s in self.anchor_sizes], "anchor_y": self.anchor_y,
                "prior_probability": self.prior_probability}

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """features: B×F×Z×Y×X -> (objectness logits B×N, deltas B×N×6), N = Zc·Xc·A (anchor order)."""
        check_shape("features", features, (None, self.in_channels, *self.grid.shape_zyx))
        B = features.shape[0]
        A = self.num_anchors_per_cell
        coarse = self.neck3d(features)                               # B×C×Zc×Yc×Xc
        _, C, Zc, Yc, Xc = coarse.shape
        bev = coarse.permute(0, 1, 3, 2, 4).reshape(B, C * Yc, Zc, Xc)  # B×(C·Yc)×Zc×Xc
        hidden = self.neck2d(bev)                                    # B×H×Zc×Xc
        logits = self.objectness(hidden).permute(0, 2, 3, 1).reshape(B, Zc * Xc * A)  # B×N
        deltas = (self.deltas(hidden).reshape(B, A, 6, Zc, Xc)      # B×A×6×Zc×Xc
                  .permute(0, 3, 4, 1, 2).reshape(B, Zc * Xc * A, 6))  # B×N×6
        return logits, deltas

    @torch.no_grad()
    def decode(self, logits: torch.Tensor, deltas: torch.Tensor, *, min_score: float = 0.0,
               nms_iou: float = 0.3, pre_nms: int = 500, max_boxes: int = 50) -> list[dict[str, torch.Tensor]]:
        """Scores and boxes from the head's outputs: logits B×N, deltas B×N×6 -> per batch item
        dict(boxes K×7 canonical in ref with yaw 0, scores K in (0, 1)), best first, after keeping the
        `pre_nms` best anchors above `min_score`, 3D NMS at `nms_iou` and at most `max_boxes`."""
        scores = torch.sigmoid(logits)                               # B×N
        out = []
        for b in range(scores.shape[0]):
            s = scores[b]
            top = torch.argsort(s, descending=True)[:pre_nms]
            top = top[s[top] >= min_score]
            aabb = decode_deltas(self.anchors[top], deltas[b, top])  # K×6
            keep = nms_aabb(aabb, s[top], nms_iou)[:max_boxes]
            out.append({"boxes": aabb_to_boxes(aabb[keep]), "scores": s[top][keep]})
        return out

    def detect(self, features: torch.Tensor, **decode_options) -> list[dict[str, torch.Tensor]]:
        """features: B×F×Z×Y×X -> per batch item dict(boxes K×7 in ref, yaw 0; scores K); see `decode`."""
        logits, deltas = self.forward(features)
        return self.decode(logits, deltas, **decode_options)
