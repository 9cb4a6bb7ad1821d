"""Conv3d that runs oneDNN (mkldnn) on CPU where PyTorch's kernel choice falls back to its slow native path.

PyTorch picks oneDNN for a CPU float32 convolution only if, among other things, the batch is > 1 or
N·C·D·H > 20480 — a rule written for 2D images. Our volumes are small along C·Z·Y, so single-example
inference (the services, the stream bridge) of every 3×3×3 conv went to `slow_conv3d`. Measured on
1 thread: a 1×46×16×4×16 input with 32 3×3×3 filters took 3.10 ms native vs 0.83 ms oneDNN, and
1×46×32×8×32 took 46.6 ms vs 6.6 ms. Outputs agree to float rounding (~1e-4 on sums of ~1000 terms)
and autograd works through `torch.mkldnn_convolution`. 1×1×1 kernels keep PyTorch's choice (there
its native path is the faster one single-threaded). Same parameters and state dict as nn.Conv3d, so
bundles load unchanged.

The direct call is for eager float32 only. Under autocast the convolution goes through F.conv3d,
which autocast casts to bfloat16 — and PyTorch sends every CPU bf16 convolution to oneDNN whatever its
size, so the batch-1 speed-up holds there too (calling torch.mkldnn_convolution under autocast kept the
convs in float32: autocast does not cover that op). Under torch.compile F.conv3d is what Inductor
lowers (it cannot trace torch.mkldnn_convolution: "itensor_view_from_dense expects CPU tensor input").
"""

from __future__ import annotations

import torch
from torch import nn


def _onednn_usable(x: torch.Tensor) -> bool:
    return (x.device.type == "cpu" and x.dtype == torch.float32 and x.dim() == 5
            and torch.backends.mkldnn.is_available() and torch.backends.mkldnn.enabled)


class Conv3d(nn.Conv3d):
    """nn.Conv3d (B×Cin×Z×Y×X -> B×Cout×Z'×Y'×X'), oneDNN on CPU float32 for kernels larger than 1³."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # is_compiling first: Dynamo may not trace the oneDNN availability checks behind it.
        if (not torch.compiler.is_compiling() and self.padding_mode == "zeros" and not isinstance(self.padding, str)
                and self.kernel_size != (1, 1, 1) and not torch.is_autocast_enabled(x.device.type)
                and _onednn_usable(x)):
            return torch.mkldnn_convolution(x, self.weight, self.bias, self.padding, self.stride, self.dilation,
                                            self.groups)  # B×Cout×Z'×Y'×X'
        return super().forward(x)
