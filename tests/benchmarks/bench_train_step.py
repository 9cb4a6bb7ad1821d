"""Benchmark: pretraining train-step time and peak memory per preset (prints figures; not a test).

CPU: full step (forward + backward + Adam) for `tiny` and `small`; for `paper` only the 3D encoder
forward+backward at 128×32×128 × 4 channels, batch 1 (a full paper step is GPU work).
CUDA: the full step at each preset (paper at batch 4) with optional bf16 autocast (--amp), then the
largest grid (paper grid scaled up in steps) whose full step fits in memory.

    python tests/benchmarks/bench_train_step.py --device cpu --preset tiny --steps 5
    python tests/benchmarks/bench_train_step.py --device cuda --preset paper --amp --steps 20
"""

from __future__ import annotations

import argparse
import contextlib
import os
import resource
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import torch  # noqa: E402

from core.data.batch import records_to_batch  # noqa: E402
from core.geometry.grid import GridConfig  # noqa: E402
from core.models.encoder3d import Encoder3D  # noqa: E402
from core.presets import get_preset  # noqa: E402
from core.synthetic import generate_record  # noqa: E402
from core.tasks import build_task  # noqa: E402


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _peak_mb(device: str) -> float:
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # process peak RSS (Linux: KiB)


def _autocast(device: str, amp: bool):
    if not amp:
        return contextlib.nullcontext()
    return torch.autocast(device_type="cuda" if device.startswith("cuda") else "cpu", dtype=torch.bfloat16)


def time_step(step, device: str, steps: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        step()
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    _sync(device)
    return (time.perf_counter() - t0) / steps


def bench_full_step(preset, *, device: str, steps: int, amp: bool, objective: str, batch_size: int) -> dict:
    gen_device = device if device.startswith("cuda") else "cpu"
    records = [generate_record(preset, seed=s, num_frames=1, device=gen_device) for s in range(batch_size)]
    batch = records_to_batch(records, device)
    task = build_task("pretrain", preset, objective=objective, seed=0).to(device)
    opt = torch.optim.Adam(task.parameters(), lr=1e-3)

    def step():
        with _autocast(device, amp):
            out = task(batch)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()

    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    sec = time_step(step, device, steps)
    return {"s_per_step": sec, "peak_mb": _peak_mb(device)}


def bench_encoder(grid_zyx, *, device: str, steps: int, amp: bool, width: int, batch_size: int = 1) -> dict:
    enc = Encoder3D(in_channels=4, width=width, out_channels=32).to(device)
    x = torch.randn(batch_size, 4, *grid_zyx, device=device)

    def step():
        with _autocast(device, amp):
            y = enc(x)
        y.float().square().mean().backward()

    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    sec = time_step(step, device, steps, warmup=1)
    return {"s_per_step": sec, "peak_mb": _peak_mb(device)}


def largest_grid(preset, *, device: str, amp: bool, objective: str, batch_size: int) -> None:
    """Scale the paper grid (same metres, more voxels) until the full step runs out of memory."""
    base = preset.grid
    for factor in (1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0):
        g = GridConfig(xmin=base.xmin, xmax=base.xmax, ymin=base.ymin, ymax=base.ymax, zmin=base.zmin,
                       zmax=base.zmax, Z=int(base.Z * factor), Y=int(base.Y * factor), X=int(base.X * factor))
        try:
            r = bench_full_step(preset.with_overrides(grid=g), device=device, steps=3, amp=amp,
                                objective=objective, batch_size=batch_size)
        except torch.OutOfMemoryError:
            print(f"grid {g.Z}x{g.Y}x{g.X} batch {batch_size}: out of memory")
            torch.cuda.empty_cache()
            return
        print(f"grid {g.Z}x{g.Y}x{g.X} batch {batch_size}: {r['s_per_step']:.3f} s/step, peak {r['peak_mb']:.0f} MiB")
        torch.cuda.empty_cache()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="all", help="tiny | small | paper | all")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--amp", action="store_true", help="torch.autocast bf16")
    ap.add_argument("--objective", default="contrastive", choices=("contrastive", "regression"))
    ap.add_argument("--batch-size", type=int, default=None, help="default: the preset's")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument("--largest-grid", action="store_true", help="CUDA: also search the largest grid that fits")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    names = ["tiny", "small", "paper"] if args.preset == "all" else [args.preset]
    dev_name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"cpu ({torch.get_num_threads()} threads)"
    print(f"device {dev_name}, torch {torch.__version__}, amp={args.amp}, objective={args.objective}")
    for name in names:
        preset = get_preset(name)
        bs = args.batch_size or preset.train.batch_size
        if name == "paper" and not args.device.startswith("cuda"):
            r = bench_encoder(preset.grid.shape_zyx, device=args.device, steps=args.steps, amp=args.amp,
                              width=preset.encoder_width)
            print(f"paper 3D encoder fwd+bwd {preset.grid.Z}x{preset.grid.Y}x{preset.grid.X}x4 batch 1: "
                  f"{r['s_per_step']:.3f} s/iter, peak RSS {r['peak_mb']:.0f} MiB")
            continue
        r = bench_full_step(preset, device=args.device, steps=args.steps, amp=args.amp,
                            objective=args.objective, batch_size=bs)
        mem = "peak CUDA" if args.device.startswith("cuda") else "peak RSS"
        print(f"{name} full step batch {bs}: {r['s_per_step']:.3f} s/iter, {mem} {r['peak_mb']:.0f} MiB")
    if args.largest_grid and args.device.startswith("cuda"):
        paper = get_preset("paper")
        largest_grid(paper, device=args.device, amp=args.amp, objective=args.objective,
                     batch_size=args.batch_size or paper.train.batch_size)


if __name__ == "__main__":
    main()
