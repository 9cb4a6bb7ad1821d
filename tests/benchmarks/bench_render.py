"""Benchmark the synthetic world: rendered view-frames per second (one view at one time step = one
view-frame) for the paper preset camera (128×384) and the tiny preset (64×192). Prints figures; not a test.

    python tests/benchmarks/bench_render.py [--threads 1 2] [--processes 2] [--repeats 5]
                                            [--omp-wait-policy passive] [--cuda]

Rows:
- `1 proc × k thr`: generate_record in this process with k torch intra-op threads (median of --repeats
  records after a warm-up): wall rate, and view-frames per CPU-second of the process.
- `N proc × 1 thr`: N worker processes of one thread each rendering records in order, exactly as
  `n3dmap data generate --jobs N` does (services/cli/render_pool.py): aggregate wall rate over the
  last three quarters of the records (steady state; the end-to-end rate with the workers' start-up
  is printed after the row); view-frames per CPU-second of
  the workers (read from /proc); and N × that, the rate N idle cores would give (the processes share
  nothing but memory bandwidth, so they scale; threads do not, so their rows have no such estimate).
  `--jobs 1` is the in-process path of `data generate --jobs 1` (one torch thread).

Wall figures on a shared machine are depressed by other jobs: the CPU count and the load average
(before and after) are printed with them. `--omp-wait-policy` sets OMP_WAIT_POLICY before torch loads
(with k > 1 threads on a busy machine the default spinning OpenMP barrier collapses throughput).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def _parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="*", default=[1, 2],
                        help="torch threads of the single-process rows (default: 1 2; none: skip)")
    parser.add_argument("--processes", type=int, nargs="*", default=[2],
                        help="render-process counts of the pooled rows (default: 2; none: skip)")
    parser.add_argument("--repeats", type=int, default=5, help="records per single-process row")
    parser.add_argument("--pool-records", type=int, default=24,
                        help="records per process in the pooled rows at the paper preset; smaller presets "
                             "render proportionally more (default: 24)")
    parser.add_argument("--presets", nargs="+", default=["paper", "tiny"])
    parser.add_argument("--omp-wait-policy", choices=["passive", "active"], default=None,
                        help="set OMP_WAIT_POLICY for this process (before torch is imported)")
    parser.add_argument("--cuda", action="store_true", help="also time rendering on CUDA when available")
    return parser.parse_args()


PAPER_PIXELS = 2 * 6 * 128 * 384  # T·V·H·W of a paper-preset record


def _pixels(preset) -> int:
    return preset.num_frames * preset.num_views * preset.camera.H * preset.camera.W


def _load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def _single_process(preset, threads: int, repeats: int, device: str) -> tuple[float, float]:
    """(wall view-frames/s, view-frames per CPU-second) of generate_record in this process (medians)."""
    import torch

    from core.synthetic import generate_record

    torch.set_num_threads(threads)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    vf = preset.num_frames * preset.num_views
    generate_record(preset, seed=10_000, moving_ego=True, device=device)  # warm-up
    sync()
    walls, cpus = [], []
    for seed in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        generate_record(preset, seed=seed, moving_ego=True, device=device)
        sync()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return vf / statistics.median(walls), vf / statistics.median(cpus)


def _children_cpu_seconds() -> float:
    """User + system CPU seconds of this process's live children (the render workers), from /proc."""
    me, ticks, total = os.getpid(), os.sysconf("SC_CLK_TCK"), 0
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == me:
            total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14, 15 of stat)
    return total / ticks


def _pooled(preset, processes: int, records_per_process: int) -> tuple[float, float, float]:
    """(end-to-end wall view-frames/s including the workers' start-up, steady-state wall view-frames/s,
    view-frames per CPU-second of the workers in the steady state) with `processes` render workers
    rendering in order, as `data generate --jobs` does.

    Steady state = after the first quarter of the records: a worker still starting up (importing torch
    takes seconds on a busy machine) lets the others take the first records, so "each worker's first
    record" cannot be told from the arrival order."""
    from services.cli.render_pool import RecordSpec, render_records

    total = processes * records_per_process
    warm = max(processes, total // 4) - 1  # the clock starts when this record arrives
    specs = [RecordSpec(preset=preset.name, seed=i, moving_ego=True) for i in range(total)]
    vf = preset.num_frames * preset.num_views
    arrivals, cpu_marks = [], {}
    # jobs=1 renders in this process (as `--jobs 1` does): its own CPU time then, not its children's.
    cpu_seconds = _children_cpu_seconds if processes > 1 else time.process_time
    t0 = time.perf_counter()
    for i, _ in enumerate(render_records(specs, jobs=processes)):
        arrivals.append(time.perf_counter())
        if i in (warm, total - 1):
            cpu_marks[i] = cpu_seconds()
    timed_vf = (total - 1 - warm) * vf
    cpu = cpu_marks[total - 1] - cpu_marks[warm]
    return (total * vf / (arrivals[-1] - t0), timed_vf / (arrivals[-1] - arrivals[warm]),
            timed_vf / cpu if cpu > 0 else float("nan"))


def main() -> None:
    args = _parse()
    if args.omp_wait_policy:
        os.environ["OMP_WAIT_POLICY"] = args.omp_wait_policy.upper()
    import torch

    from core.presets import get_preset
    from services.threads import usable_cpus

    presets = [get_preset(name) for name in args.presets]
    print(f"torch {torch.__version__}; {usable_cpus()} usable CPUs (os.cpu_count {os.cpu_count()}); "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}; load average {_load()} (1/5/15 min)")
    print(f"{'preset':7} {'H×W':>8} {'T×V':>4} {'device':6} {'run':>18} {'wall VF/s':>10} "
          f"{'VF per CPU-s':>12} {'idle N-core est.':>16} {'load 1 min':>10}")
    for preset in presets:
        shape = f"{preset.camera.H:>3}×{preset.camera.W:<4} {preset.num_frames}×{preset.num_views:<2}"
        for threads in args.threads:
            wall, cpu = _single_process(preset, threads, args.repeats, "cpu")
            print(f"{preset.name:7} {shape} {'cpu':6} {f'1 proc × {threads} thr':>18} {wall:10.1f} {cpu:12.1f} "
                  f"{'':>16} {os.getloadavg()[0]:10.2f}", flush=True)
        for processes in args.processes:
            per_process = args.pool_records * max(1, PAPER_PIXELS // _pixels(preset))
            end_to_end, wall, cpu = _pooled(preset, processes, per_process)
            run = f"{processes} proc × 1 thr" if processes > 1 else "--jobs 1 (in-proc)"
            print(f"{preset.name:7} {shape} {'cpu':6} {run:>18} {wall:10.1f} {cpu:12.1f} "
                  f"{processes * cpu:16.1f} {os.getloadavg()[0]:10.2f}   end-to-end {end_to_end:.1f} VF/s "
                  f"({processes * per_process} records incl. start-up)", flush=True)
        if args.cuda and torch.cuda.is_available():
            wall, _ = _single_process(preset, 1, args.repeats, "cuda")
            print(f"{preset.name:7} {shape} {'cuda':6} {'1 proc':>18} {wall:10.1f} {'':>12} {'':>16} "
                  f"{os.getloadavg()[0]:10.2f}", flush=True)
    print(f"load average at the end {_load()}")


if __name__ == "__main__":
    main()
