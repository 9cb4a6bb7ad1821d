"""Benchmark: the paper-grid 3D encoder against the machine's own matrix-multiply rate (prints figures).

In one process, alternating so that both see the same load: a 2048² float32 matrix product (SGEMM, the
rate the machine can reach) and the 3D encoder (core.models.encoder3d, the paper's widths: 4 → 64, F 32)
on a 1×4×128×32×128 volume — its inference forward in float32, and forward+backward in float32 and under
bf16 autocast. Printed: each median time, the encoder's arithmetic rate (multiply-adds of its
convolutions counted from their shapes, ×2 FLOP) as a fraction of the SGEMM rate, the bf16 speed-up, the
share of the forward spent outside the convolutions (the full-resolution tail: trilinear upsample and L2
normalisation, from torch.profiler), that tail alone in channels-first and in channels-last layout and its
forward+backward as plain ops and as the fused step the encoder uses on CPU (core/models/encoder3d.py,
"Tail"), and the load average. One JSON
line, then a summary.

    python tests/benchmarks/bench_encoder.py                       # 2 threads, paper grid
    python tests/benchmarks/bench_encoder.py --malloc tuned        # glibc: no mmap'd chunks, no trimming
    python tests/benchmarks/bench_encoder.py --grid 64 16 64 --width 16 --out-channels 16 --threads 1

--malloc tuned (glibc only) applies `services.malloc.keep_heap()` before any tensor exists, as every n3dmap
CLI command but `serve` does: M_MMAP_MAX 0 (every chunk from the heap, even the 64 MiB feature maps, which
glibc would otherwise map fresh on each allocation and fault in page by page) and M_TRIM_THRESHOLD 1 GiB
(freed heap is kept for the next step). --malloc default leaves glibc's settings (this script does not go
through the CLI). See README "Performance" for the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

def conv_macs(model, x) -> int:
    """Multiply-adds of every Conv3d / ConvTranspose3d in one forward of `model` on x, from the shapes."""
    import torch
    from torch import nn

    total = 0

    def hook(module, inputs, output):
        nonlocal total
        k = 1
        for n in module.kernel_size:
            k *= n
        if isinstance(module, nn.ConvTranspose3d):  # every input voxel meets every kernel tap once
            total += inputs[0].numel() * module.out_channels // module.groups * k
        else:
            total += output.numel() * module.in_channels // module.groups * k

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, (nn.Conv3d, nn.ConvTranspose3d))]
    with torch.no_grad():
        model(x)
    for h in handles:
        h.remove()
    return total


def median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up: oneDNN builds its kernels, the allocator grows
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def tail_share(encoder, x) -> dict:
    """Shares of the forward's self CPU time: convolutions, and the named tail ops."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    from tests.benchmarks.step_profile import is_conv_op

    with torch.no_grad(), profile(activities=[ProfilerActivity.CPU]) as prof:
        encoder(x)
    rows = {e.key: e.self_cpu_time_total for e in prof.key_averages()}
    total = sum(rows.values()) or 1.0
    tail = {name: rows.get(name, 0.0) / total for name in ("aten::upsample_trilinear3d", "aten::mul", "aten::sum",
                                                             "aten::linalg_vector_norm", "aten::div")}
    return {"conv": sum(v for k, v in rows.items() if is_conv_op(k)) / total,
            **{k.removeprefix("aten::"): round(v, 3) for k, v in tail.items() if v > 0}}


def tail_layouts(out_channels: int, grid, repeats: int) -> dict:
    """Median ms of the encoder's tail (trilinear ×2 upsample of the half-resolution F-channel output, then
    L2 normalisation): forward in channels-first layout (the reference) and channels-last (conversion
    included), and forward + backward (a channels-first incoming gradient) of the plain ops against the
    fused step the encoder uses on CPU (core.models.upsample_normalize)."""
    import torch
    import torch.nn.functional as F

    from core.models.normalize import l2_normalize_channels
    from core.models.upsample_normalize import upsample_normalize

    half = torch.randn(1, out_channels, *(n // 2 for n in grid))  # 1×F×Z/2×Y/2×X/2
    grad = torch.randn(1, out_channels, *grid)                     # 1×F×Z×Y×X

    def plain(x):
        return l2_normalize_channels(F.interpolate(x, size=tuple(grid), mode="trilinear", align_corners=False))

    def forward(layout):
        def run():
            plain(half.contiguous(memory_format=layout))
        return run

    def forward_backward(fn):
        def run():
            x = half.clone().requires_grad_()
            fn(x).backward(grad)
        return run

    return {"tail_channels_first_ms": round(median_seconds(forward(torch.contiguous_format), repeats) * 1e3, 2),
            "tail_channels_last_ms": round(median_seconds(forward(torch.channels_last_3d), repeats) * 1e3, 2),
            "tail_fwd_bwd_plain_ms": round(median_seconds(forward_backward(plain), repeats) * 1e3, 2),
            "tail_fwd_bwd_fused_ms": round(median_seconds(forward_backward(
                lambda x: upsample_normalize(x, tuple(grid))), repeats) * 1e3, 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--grid", type=int, nargs=3, default=(128, 32, 128), metavar=("Z", "Y", "X"))
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--out-channels", type=int, default=32)
    ap.add_argument("--malloc", choices=("default", "tuned"), default="default")
    ap.add_argument("--no-backward", action="store_true", help="forward only (skip the fwd+bwd and bf16 rows)")
    args = ap.parse_args(argv)
    from services.malloc import keep_heap

    tuned = keep_heap() if args.malloc == "tuned" else False

    import torch

    from core.models.encoder3d import Encoder3D

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    encoder = Encoder3D(in_channels=4, width=args.width, out_channels=args.out_channels)
    x = torch.randn(1, 4, *args.grid)
    macs = conv_macs(encoder, x)

    def sgemm():
        torch.mm(a, b)

    def forward():
        with torch.no_grad():
            encoder(x)

    def forward_backward(bf16: bool):
        def run():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                y = encoder(x)
            y.float().square().mean().backward()
        return run

    encoder.eval()
    rows = {"sgemm": [], "forward": []}
    for _ in range(3):  # alternate, so both see the same load
        rows["sgemm"].append(median_seconds(sgemm, args.repeats))
        rows["forward"].append(median_seconds(forward, args.repeats))
    sgemm_s, forward_s = min(rows["sgemm"]), min(rows["forward"])
    sgemm_gflops = 2 * 2048 ** 3 / sgemm_s / 1e9
    encoder_gflops = 2 * macs / forward_s / 1e9
    result = {"grid": list(args.grid), "width": args.width, "out_channels": args.out_channels, "threads": args.threads,
              "malloc": args.malloc, "malloc_tuned": tuned, "conv_gmac": round(macs / 1e9, 2),
              "sgemm_gflops": round(sgemm_gflops, 1), "forward_s": round(forward_s, 4),
              "encoder_gflops": round(encoder_gflops, 1), "ratio_to_sgemm": round(encoder_gflops / sgemm_gflops, 3),
              "forward_shares": tail_share(encoder, x), **tail_layouts(args.out_channels, args.grid, args.repeats)}
    if not args.no_backward:
        encoder.train()
        fp32 = median_seconds(forward_backward(False), args.repeats)
        bf16 = median_seconds(forward_backward(True), args.repeats)
        result.update(fwd_bwd_fp32_s=round(fp32, 4), fwd_bwd_bf16_s=round(bf16, 4), bf16_speedup=round(fp32 / bf16, 3))
    result["load_avg"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(result), flush=True)
    print(f"encoder {'×'.join(map(str, args.grid))} width {args.width}: forward {forward_s * 1e3:.0f} ms = "
          f"{encoder_gflops:.0f} GFLOP/s = {encoder_gflops / sgemm_gflops:.2f} × SGEMM ({sgemm_gflops:.0f} GFLOP/s), "
          f"{args.threads} threads, malloc {args.malloc}; tail (upsample + normalise) channels-first "
          f"{result['tail_channels_first_ms']:.1f} ms, channels-last {result['tail_channels_last_ms']:.1f} ms, "
          f"fwd+bwd plain {result['tail_fwd_bwd_plain_ms']:.1f} ms, fused {result['tail_fwd_bwd_fused_ms']:.1f} ms"
          + (f"; fwd+bwd fp32 {result['fwd_bwd_fp32_s']:.3f} s, bf16 {result['fwd_bwd_bf16_s']:.3f} s "
             f"({result['bf16_speedup']:.2f}×)" if not args.no_backward else "")
          + f"; load {result['load_avg']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
