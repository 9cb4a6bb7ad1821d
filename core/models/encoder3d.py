"""3D encoder-decoder with skips: the feature extractor of the neural 3D mapper (paper appendix).

Layers in kernel-stride-channels notation (C = `width`, F = `out_channels`):
    4-2-C, 4-2-2C, 4-2-4C,          encoder (three stride-2 convs)
    4-0.5-2C  ++ skip(2C),           decoder (transposed convs, then concat the encoder map of
    4-0.5-C   ++ skip(C),            the same resolution)
    1-1-F                            output
Every conv except the last is followed by LeakyReLU then BatchNorm (the paper's order).

Resolution: the paper's layer list ends at half the input resolution. We upsample the F-channel
output trilinearly to the input grid (Z×Y×X) and then L2-normalise each voxel's feature, so every
downstream part sees features at grid resolution. Inputs of any size work: the volume is
zero-padded to a multiple of 8 per axis before the encoder and the output is cropped back.

`full_res` > 0 (not in the paper; presets default to 0) adds a full-resolution branch: a 3×3×3 conv of
the input volume to `full_res` channels (LeakyReLU), concatenated with the upsampled output and fused by
a 1×1 conv back to F channels before the normalisation. Why: three stride-2 stages make the paper's
layers equivariant only to shifts by multiples of 8 voxels, so an object moved by 1-3 voxels gets
different features, and 3D flow over the maps cannot see the move. Measured on a small contrastive
mapper (tests/benchmarks/bench_flow_features.py, one seed): moving only an object's input voxels by
1/2/3 voxels, the cosine margin of the true shift over zero was −0.04/−0.03/−0.05 with the paper's
layers and +0.08/+0.10/+0.16 with a 16-channel branch; free-space occupancy accuracy 0.951 → 0.975.
On real frame pairs the margin stays negative (−0.07 → −0.05), so the branch is necessary for flow over
maps but not sufficient. It costs about as much as the rest of the encoder at the small preset's width
(forward+backward of 8 small-grid volumes, width 16, 1 thread: 0.28 s → 0.54 s).

Tail: on CPU, the upsample and the normalisation are one fused step in channels-last layout
(core.models.upsample_normalize, its own forward and backward; the features come back with channels-last
strides: same shape and values, `.contiguous()` gives the usual layout). With the full-resolution branch
or without normalisation, the two plain ops run, in channels-last only without gradients. Measured
(tests/benchmarks/bench_encoder.py prints the tail in both layouts): paper grid, 2 threads, forward
36.7 → 15.6 ms and forward + backward 98.7 → 61.7 ms; small grid, 1 thread, 4.0 → 1.0 ms and 11.3 → 5.9 ms.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import check_shape
from core.models.normalize import l2_normalize_channels
from core.models.conv3d import Conv3d, ConvTranspose3d
from core.models.upsample_normalize import upsample_normalize


def _conv_block(conv: nn.Module, channels: int) -> nn.Sequential:
    return nn.Sequential(conv, nn.LeakyReLU(0.1, inplace=True), nn.BatchNorm3d(channels))


class Encoder3D(nn.Module):
    """B×Cin×Z×Y×X volume -> B×F×Z×Y×X per-voxel unit-length features."""

    def __init__(self, *, in_channels: int = 4, width: int = 64, out_channels: int = 32,
                 normalize: bool = True, full_res: int = 0) -> None:
        super().__init__()
        self.in_channels, self.width, self.out_channels = in_channels, width, out_channels
        self.normalize = normalize
        self.full_res = int(full_res)
        if self.full_res > 0:
            self.skip0 = nn.Sequential(Conv3d(in_channels, self.full_res, 3, padding=1),
                                       nn.LeakyReLU(0.1, inplace=True))
            self.fuse0 = Conv3d(out_channels + self.full_res, out_channels, 1)
        C = width
        self.down1 = _conv_block(Conv3d(in_channels, C, 4, stride=2, padding=1), C)
        self.down2 = _conv_block(Conv3d(C, 2 * C, 4, stride=2, padding=1), 2 * C)
        self.down3 = _conv_block(Conv3d(2 * C, 4 * C, 4, stride=2, padding=1), 4 * C)
        self.up1 = _conv_block(ConvTranspose3d(4 * C, 2 * C, 4, stride=2, padding=1), 2 * C)
        self.up2 = _conv_block(ConvTranspose3d(4 * C, C, 4, stride=2, padding=1), C)
        self.out = Conv3d(2 * C, out_channels, 1)

    def config(self) -> dict:
        return {"in_channels": self.in_channels, "width": self.width,
                "out_channels": self.out_channels, "normalize": self.normalize, "full_res": self.full_res}

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        """volume: B×Cin×Z×Y×X -> features B×F×Z×Y×X (unit L2 norm per voxel if `normalize`)."""
        check_shape("volume", volume, (None, self.in_channels, None, None, None))
        Z, Y, X = volume.shape[-3:]
        pad = [(-n) % 8 for n in (X, Y, Z)]  # F.pad order: last dim first
        x0 = F.pad(volume, (0, pad[0], 0, pad[1], 0, pad[2]))  # B×Cin×Z8×Y8×X8 (multiples of 8)
        x1 = self.down1(x0)   # B×C×Z/2×…
        x2 = self.down2(x1)   # B×2C×Z/4×…
        x3 = self.down3(x2)   # B×4C×Z/8×…
        u1 = torch.cat([self.up1(x3), x2], dim=1)  # B×4C×Z/4×…
        u2 = torch.cat([self.up2(u1), x1], dim=1)  # B×2C×Z/2×…
        feat = self.out(u2)                        # B×F×Z/2×…
        if self.normalize and self.full_res == 0 and feat.device.type == "cpu":  # module docstring, "Tail"
            return upsample_normalize(feat, x0.shape[-3:])[..., :Z, :Y, :X]  # B×F×Z×Y×X (crop the padding)
        if feat.device.type == "cpu" and not (torch.is_grad_enabled() and feat.requires_grad):
            feat = feat.contiguous(memory_format=torch.channels_last_3d)  # B×F×Z/2×… (strides F last)
        feat = F.interpolate(feat, size=x0.shape[-3:], mode="trilinear", align_corners=False)
        feat = feat[..., :Z, :Y, :X]               # B×F×Z×Y×X (crop the padding)
        if self.full_res > 0:
            feat = self.fuse0(torch.cat([feat, self.skip0(volume)], dim=1))  # B×F×Z×Y×X
        if self.normalize:
            feat = l2_normalize_channels(feat)
        return feat
