"""Benchmark: train-step time and peak memory, per preset or per task (prints figures; not a test).

Pretraining mode (the default, no --tasks):
CPU: full step (forward + backward + Adam) for `tiny` and `small`; for `paper` only the 3D encoder
forward+backward at 128×32×128 × 4 channels, batch 1 (a full paper step is GPU work).
CUDA: the full step at each preset (paper at batch 4) with optional bf16 autocast (--precision bf16,
alias --amp), then the largest grid (paper grid scaled up in steps) whose full step fits in memory.

    python tests/benchmarks/bench_train_step.py --device cpu --preset tiny --steps 5
    python tests/benchmarks/bench_train_step.py --device cuda --preset paper --precision bf16 --steps 20
    python tests/benchmarks/bench_train_step.py --device cpu --preset small --widths 64 32 32 --threads 1

--widths W F E replaces the preset's encoder width, feature channels F and embedding channels E (the
paper's are 64 32 32; small's 16 16 16), to price the paper's model on a preset's grid.

Per-task mode (--tasks, CPU only, presets tiny and small; --preset all = both): for each (task,
preset) row, every task of core.tasks.build_task (pretrain = contrastive, pretrain_regression =
pretrain with objective="regression", egomotion, occupancy, flow, flow_features = flow over the
mapper's features with the README's recipe, detector; flow and detector keep their untrained mapper
frozen, as built, and flow's default "volume" inputs do not run it) on a batch
of the preset's batch size of synthetic records (generate_record, moving_ego=True, T=2): --warmup
untimed steps, then --steps timed steps of forward + backward + Adam (over the parameters that
require grad, as services/training/loop.py does), each timed alone (median and mean), then
--profile-steps more steps under torch.profiler (CPU activity). --threads defaults to 1 here (and
sets OMP_NUM_THREADS/MKL_NUM_THREADS of the row subprocesses). --precision bf16 runs each forward (the
task's loss included) under CPU bf16 autocast, as `n3dmap train --precision bf16` does.

    python tests/benchmarks/bench_train_step.py --tasks --preset tiny --threads 1 --steps 3
    python tests/benchmarks/bench_train_step.py --tasks flow,detector --preset small --threads 1
    python tests/benchmarks/bench_train_step.py --tasks all --preset small --threads 1 --precision bf16

Every row runs in a fresh subprocess (this file with --row), so one row's memory, allocator caches
and thread pools do not leak into the next. Each row prints one JSON line:
  {"task", "preset", "precision", "threads", "steps", "step_s_median", "step_s_mean", "conv_share", "peak_rss_mb",
   "top_non_conv": [[op, share], ...], "load_avg", "rss_before_task_mb", "conv_ops"}
and a table follows the last row.
- conv_share: convolution ops' share of the self CPU time of the profiled steps (the sum of every
  op's self time; Python time between ops is not in it). Convolution ops, as counted by
  tests/benchmarks/step_profile.py (is_conv_op): names containing "convolution" (aten::convolution,
  aten::_convolution, aten::mkldnn_convolution, aten::convolution_backward,
  aten::mkldnn_convolution_backward, the autograd nodes ConvolutionBackward0 /
  MkldnnConvolutionBackward0 and their "autograd::engine::evaluate_function:" wrappers) or "conv" + a
  digit / "_transpose" / "_depthwise" / "_tbc" (aten::conv2d, aten::conv3d, aten::conv_transpose3d,
  aten::slow_conv3d, aten::slow_conv3d_forward, aten::thnn_conv2d, aten::_slow_conv2d_forward,
  aten::_slow_conv2d_backward, ...); "conv_ops" lists the names counted in that row. top_non_conv:
  the 5 other ops with the most self CPU time, each with its share of the same total. Profiler
  overhead inflates small ops a little; step times come from the unprofiled steps.
- peak_rss_mb: the row subprocess's peak resident set (getrusage(RUSAGE_SELF).ru_maxrss) after the
  timed steps: torch import, record generation and the steps; rss_before_task_mb is the same
  high-water mark just before the task is built (imports + records), so the difference bounds what
  the task and its steps added. (tracemalloc misses torch's C++ allocations.)
- load_avg: os.getloadavg() at the end of the row: on a shared machine, times are only comparable
  between rows taken under similar load.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import statistics
import subprocess
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
from tests.benchmarks.step_profile import conv_share, is_conv_op, matched_ops, top_ops  # noqa: E402

# Per-task mode: row name -> (core.tasks name, build_task options).
TASK_VARIANTS: dict[str, tuple[str, dict]] = {
    "pretrain": ("pretrain", {"objective": "contrastive"}),
    "pretrain_regression": ("pretrain", {"objective": "regression"}),
    "egomotion": ("egomotion", {}),
    "occupancy": ("occupancy", {}),
    "flow": ("flow", {}),
    # the recipe of flow over features (README "Benchmarks"): frozen matching-trained mapper, ±3/±1/±3 grid step
    # with box-aggregated costs (its cost volume and box mean have hand-written backwards)
    "flow_features": ("flow", {"inputs": "features", "refine_radius": (3, 1, 3), "refine_aggregate": (1, 1, 1),
                               "encoder_full_res": 16}),
    "detector": ("detector", {}),
}
CPU_PRESETS = ("tiny", "small")


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


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def profile_task_step(task_name: str, preset_name: str, *, steps: int, warmup: int = 2,
                      profile_steps: int = 2, threads: int = 1, precision: str = "fp32") -> dict:
    """One per-task row, in this process (see the module docstring); returns the row's dict."""
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    base, options = TASK_VARIANTS[task_name]
    preset = get_preset(preset_name)
    records = [generate_record(preset, seed=s, num_frames=2, moving_ego=True)
               for s in range(preset.train.batch_size)]
    batch = records_to_batch(records, "cpu")
    rss_before = _rss_mb()
    task = build_task(base, preset, seed=0, **options)
    task.train()
    opt = torch.optim.Adam([p for p in task.parameters() if p.requires_grad], lr=1e-3)

    def step():
        with _autocast("cpu", precision == "bf16"):
            out = task(batch)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()

    for _ in range(warmup):
        step()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    peak = _rss_mb()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for _ in range(profile_steps):
            step()
    events = list(prof.events())
    return {
        "task": task_name, "preset": preset_name, "precision": precision, "threads": torch.get_num_threads(),
        "steps": steps,
        "step_s_median": statistics.median(times), "step_s_mean": statistics.fmean(times),
        "conv_share": conv_share(events, is_conv_op), "peak_rss_mb": peak,
        "top_non_conv": [[name, share] for name, share in top_ops(events, 5, exclude=is_conv_op)],
        "load_avg": list(os.getloadavg()), "rss_before_task_mb": rss_before,
        "conv_ops": matched_ops(events, is_conv_op),
    }


def run_row_subprocess(task_name: str, preset_name: str, *, steps: int, warmup: int, profile_steps: int,
                       threads: int, precision: str = "fp32") -> dict:
    """profile_task_step in a fresh `python this_file --row TASK PRESET` process; returns its row."""
    cmd = [sys.executable, os.path.abspath(__file__), "--row", task_name, preset_name, "--steps", str(steps),
           "--warmup", str(warmup), "--profile-steps", str(profile_steps), "--threads", str(threads),
           "--precision", precision]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"row {task_name}/{preset_name} failed (exit {proc.returncode}):\n"
                           f"{proc.stdout[-2000:]}{proc.stderr[-4000:]}")
    line = next(x for x in reversed(proc.stdout.splitlines()) if x.startswith("{"))
    return json.loads(line)


def format_table(rows: list[dict]) -> str:
    """The rows as a fixed-width table (one line per row, plus a header)."""
    head = f"{'task':<20} {'preset':<6} {'prec':<4} {'thr':>3} {'median s':>9} {'mean s':>9} {'conv %':>7} " \
           f"{'peak RSS MiB':>12}  {'load 1m':>7}  top non-conv op (share)"
    lines = [head, "-" * len(head)]
    for r in rows:
        top = r["top_non_conv"][0] if r["top_non_conv"] else ["-", 0.0]
        lines.append(f"{r['task']:<20} {r['preset']:<6} {r.get('precision', 'fp32'):<4} {r['threads']:>3} "
                     f"{r['step_s_median']:>9.3f} {r['step_s_mean']:>9.3f} {100 * r['conv_share']:>6.1f}% "
                     f"{r['peak_rss_mb']:>12.0f}  "
                     f"{r['load_avg'][0]:>7.2f}  {top[0]} ({100 * top[1]:.1f}%)")
    return "\n".join(lines)


def task_mode(args) -> None:
    if args.device not in (None, "cpu"):
        raise SystemExit("--tasks runs on CPU only (--device cpu)")
    names = list(TASK_VARIANTS) if args.tasks == "all" else [t.strip() for t in args.tasks.split(",") if t.strip()]
    unknown = [t for t in names if t not in TASK_VARIANTS]
    if unknown:
        raise SystemExit(f"unknown task(s) {unknown}; choose from {sorted(TASK_VARIANTS)} or 'all'")
    presets = list(CPU_PRESETS) if args.preset == "all" else [args.preset]
    if any(p not in CPU_PRESETS for p in presets):
        raise SystemExit(f"--tasks runs the CPU presets {CPU_PRESETS} (or 'all'), got {args.preset!r}")
    threads = args.threads or 1
    print(f"per-task train step: cpu ({threads} threads), {args.precision}, torch {torch.__version__}, "
          f"warmup {args.warmup}, steps {args.steps}, profiled steps {args.profile_steps}, one subprocess per row",
          flush=True)
    rows, t0 = [], time.perf_counter()
    for preset_name in presets:
        for task_name in names:
            row = run_row_subprocess(task_name, preset_name, steps=args.steps, warmup=args.warmup,
                                     profile_steps=args.profile_steps, threads=threads, precision=args.precision)
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(format_table(rows))
    print(f"{len(rows)} rows in {time.perf_counter() - t0:.1f} s wall (subprocess start-up included)")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="all", help="tiny | small | paper | all")
    ap.add_argument("--device", default=None, help="default: cuda if available, else cpu (per-task mode: cpu)")
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                    help="bf16: the forward under torch.autocast bfloat16 (both modes)")
    ap.add_argument("--amp", action="store_true", help="alias of --precision bf16")
    ap.add_argument("--objective", default="contrastive", choices=("contrastive", "regression"))
    ap.add_argument("--batch-size", type=int, default=None, help="default: the preset's")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's; per-task mode: 1)")
    ap.add_argument("--largest-grid", action="store_true", help="CUDA: also search the largest grid that fits")
    ap.add_argument("--widths", type=int, nargs=3, default=None, metavar=("W", "F", "E"),
                    help="pretraining mode: encoder width, feature and embedding channels instead of the preset's")
    ap.add_argument("--tasks", nargs="?", const="all", default=None,
                    help="per-task mode (CPU): comma-separated tasks of " + ",".join(TASK_VARIANTS) +
                         " or 'all' (the default when --tasks has no value); --preset tiny | small | all")
    ap.add_argument("--warmup", type=int, default=2, help="per-task mode: untimed steps first")
    ap.add_argument("--profile-steps", type=int, default=2, help="per-task mode: steps under torch.profiler")
    ap.add_argument("--row", nargs=2, metavar=("TASK", "PRESET"), help=argparse.SUPPRESS)  # one row, in-process
    args = ap.parse_args(argv)
    if args.amp:
        args.precision = "bf16"
    args.amp = args.precision == "bf16"
    if args.row:
        row = profile_task_step(args.row[0], args.row[1], steps=args.steps, warmup=args.warmup,
                                profile_steps=args.profile_steps, threads=args.threads or 1,
                                precision=args.precision)
        print(json.dumps(row), flush=True)
        return
    if args.tasks is not None:
        task_mode(args)
        return
    if args.device is None:
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.threads:
        torch.set_num_threads(args.threads)
    names = ["tiny", "small", "paper"] if args.preset == "all" else [args.preset]
    dev_name = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"cpu ({torch.get_num_threads()} threads)"
    print(f"device {dev_name}, torch {torch.__version__}, precision {args.precision}, objective={args.objective}")
    for name in names:
        preset = get_preset(name)
        if args.widths:
            width, features, embed = args.widths
            preset = preset.with_overrides(encoder_width=width, feature_dim=features, embed_dim=embed)
            name = f"{name} (widths {width}/{features}/{embed})"
        bs = args.batch_size or preset.train.batch_size
        if preset.name == "paper" and not args.device.startswith("cuda"):
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
