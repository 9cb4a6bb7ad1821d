"""Bottom-up 2D network: a small residual network from the target image to an E-channel embedding.

Paper appendix: two residual blocks of three convolutions each (64, 64, 64 | 128, 128, 128), then one
convolution to E channels. Widths are constructor arguments so small presets can shrink them.
`stride=2` makes the first convolution halve the resolution, matching a projector that renders at
half image resolution.
"""

from __future__ import annotations

import torch
from torch import nn

from core.errors import check_shape
from core.models.normalize import l2_normalize_channels


class ResidualBlock2D(nn.Module):
    """Three 3×3 convs (LeakyReLU + BatchNorm after each) plus a (projected) identity shortcut."""

    def __init__(self, *, in_channels: int, out_channels: int, stride: int = 1) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = in_channels
        for i in range(3):
            layers += [nn.Conv2d(c_in, out_channels, 3, stride=stride if i == 0 else 1, padding=1),
                       nn.LeakyReLU(0.1, inplace=True), nn.BatchNorm2d(out_channels)]
            c_in = out_channels
        self.body = nn.Sequential(*layers)
        self.shortcut = (nn.Identity() if in_channels == out_channels and stride == 1
                         else nn.Conv2d(in_channels, out_channels, 1, stride=stride))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: B×Cin×H×W -> B×Cout×H'×W'."""
        return self.body(x) + self.shortcut(x)


class Net2D(nn.Module):
    """B×Cin×H×W image -> B×E×H'×W' embedding (H' = ceil(H/stride)); unit-norm if `normalize`."""

    def __init__(self, *, in_channels: int = 3, widths: tuple[int, int] = (64, 128),
                 out_channels: int = 32, stride: int = 1, normalize: bool = True) -> None:
        super().__init__()
        self.in_channels, self.widths, self.out_channels = in_channels, tuple(widths), out_channels
        self.stride, self.normalize = stride, normalize
        self.block1 = ResidualBlock2D(in_channels=in_channels, out_channels=widths[0], stride=stride)
        self.block2 = ResidualBlock2D(in_channels=widths[0], out_channels=widths[1])
        self.out = nn.Conv2d(widths[1], out_channels, 1)

    def config(self) -> dict:
        return {"in_channels": self.in_channels, "widths": list(self.widths),
                "out_channels": self.out_channels, "stride": self.stride, "normalize": self.normalize}

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """image: B×Cin×H×W (RGB in [0,1] is centred here) -> B×E×H'×W'."""
        check_shape("image", image, (None, self.in_channels, None, None))
        # contiguous(): torch 2.13 CPU segfaults in the backward of a strided 1×1 conv on a
        # channels-last input (what a permuted H×W×3 image is).
        emb = self.out(self.block2(self.block1((image - 0.5).contiguous())))
        return l2_normalize_channels(emb) if self.normalize else emb
