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

One CPU bf16 case is kept in float32 (Conv3d and ConvTranspose3d below): oneDNN 3.12's bf16 weight-gradient
kernel for 3D convolutions (`jit_bf16:avx512_core_bf16, backward_weights` in ONEDNN_VERBOSE, torch 2.13)
breaks when a strided conv's output (a transposed conv's input) has height 1 — the encoder's bottleneck
at the tiny preset (Y 8 -> 1 in down3, 1 -> 2 in up1). Measured with the bare op
(torch.ops.aten.convolution_backward on bf16 tensors, 1 thread, MALLOC_CHECK_=3): a 4³ stride-2 pad-1
conv from 16 to 32 channels over 8×2×8 (output 4×1×4) aborts with "double free or corruption" or a bus
error, batch 1 or 2; the same over 64 -> 128 channels returns NaN weight and bias gradients without a
crash; the transposed conv 32 -> 16 from 4×1×4 aborts, and from 8×1×8 gives NaN weight gradients. That
was the crash of a whole tiny training step under bf16 autocast. Height 2+ outputs, depth or width 1, a
1×1×1 output, stride 1, other pads (k4 s2 p2, k2 s2 p0), 2D convs and float32 all came out within bf16
rounding (≤ 0.6 % of the largest gradient). Workaround: under CPU autocast, a conv with stride > 1 along
a dimension whose conv-side output is 1 (any dimension, not only height: a margin on a kernel we cannot
read) runs in float32 with autocast off; its output is float32 and the next conv casts back to bf16. It
only concerns 1-voxel-thick bottlenecks (tiny: 4×1×4 voxels, the encoder's smallest tensors; small and
paper grids never get there); CUDA autocast is untouched.
"""

from __future__ import annotations

import torch
from torch import nn


def _onednn_usable(x: torch.Tensor) -> bool:
    return (x.device.type == "cpu" and x.dtype == torch.float32 and x.dim() == 5
            and torch.backends.mkldnn.is_available() and torch.backends.mkldnn.enabled)


def _bf16_weight_grad_unsafe(x: torch.Tensor, stride: tuple[int, ...], conv_out: tuple[int, ...]) -> bool:
    """True under CPU autocast for a conv whose conv-side output `conv_out` (Z, Y, X) is 1 along a strided
    dimension: oneDNN's bf16 weight gradient corrupts memory or returns NaN there (module docstring)."""
    return (x.device.type == "cpu" and torch.is_autocast_enabled("cpu")
            and any(s > 1 and n == 1 for s, n in zip(stride, conv_out)))


class Conv3d(nn.Conv3d):
    """nn.Conv3d (B×Cin×Z×Y×X -> B×Cout×Z'×Y'×X'), oneDNN on CPU float32 for kernels larger than 1³."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not isinstance(self.padding, str) and _bf16_weight_grad_unsafe(x, self.stride, self._out_size(x)):
            with torch.autocast("cpu", enabled=False):
                return self.forward(x.float())  # float32 (oneDNN where it is usable), see the module docstring
        # is_compiling first: Dynamo may not trace the oneDNN availability checks behind it.
        if (not torch.compiler.is_compiling() and self.padding_mode == "zeros" and not isinstance(self.padding, str)
                and self.kernel_size != (1, 1, 1) and not torch.is_autocast_enabled(x.device.type)
                and _onednn_usable(x)):
            return torch.mkldnn_convolution(x, self.weight, self.bias, self.padding, self.stride, self.dilation,
                                            self.groups)  # B×Cout×Z'×Y'×X'
        return super().forward(x)

    def _out_size(self, x: torch.Tensor) -> tuple[int, ...]:
        """Output Z, Y, X of this conv for input x (numeric padding)."""
        return tuple((n + 2 * p - d * (k - 1) - 1) // s + 1 for n, p, d, k, s in
                     zip(x.shape[-3:], self.padding, self.dilation, self.kernel_size, self.stride))


class ConvTranspose3d(nn.ConvTranspose3d):
    """nn.ConvTranspose3d (B×Cin×Z×Y×X -> B×Cout×Z'×Y'×X'), kept in float32 under CPU autocast where its input
    is 1 along a strided dimension (oneDNN's bf16 weight gradient breaks there; module docstring). Same
    parameters and state dict as nn.ConvTranspose3d."""

    def forward(self, x: torch.Tensor, output_size: list[int] | None = None) -> torch.Tensor:
        if _bf16_weight_grad_unsafe(x, self.stride, tuple(x.shape[-3:])):
            with torch.autocast("cpu", enabled=False):
                return super().forward(x.float(), output_size)
        return super().forward(x, output_size)
