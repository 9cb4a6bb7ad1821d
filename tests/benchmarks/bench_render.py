"""Benchmark the synthetic world: rendered view-frames per second (one view at one time step = one
view-frame) for the paper preset camera (128×384) and the tiny preset (64×192), on CPU and on CUDA
when available. Prints figures; not a test.

    python tests/benchmarks/bench_render.py [--threads 2] [--repeats 5]

Wall-clock figures on a shared machine are depressed by other jobs; the CPU-time figure (process CPU
seconds / threads) estimates what an idle machine with that many cores would give.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from core.presets import PAPER, TINY  # noqa: E402
from core.synthetic import default_world_config, generate_record  # noqa: E402
from core.synthetic.scene import sample_scene  # noqa: E402


def _time(fn, repeats: int, sync) -> tuple[float, float]:
    """(median wall seconds, median process-CPU seconds) of fn() over `repeats` runs after one warm-up."""
    fn()
    sync()
    walls, cpus = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {args.threads} CPU threads, repeats {args.repeats} (median)")
    print(f"{'preset':7} {'H×W':>8} {'T×V':>4} {'device':6} {'record s':>9} {'view-frames/s':>14} "
          f"{'CPU-time view-frames/s':>23} {'scene sampling s':>17}")
    for preset in (PAPER, TINY):
        T, V = preset.num_frames, preset.num_views
        cfg = default_world_config(preset)
        scene_wall, _ = _time(lambda: sample_scene(np.random.default_rng(1), T=T, V=V, cfg=cfg, grid=preset.grid,
                                                   ground_y=preset.ground_y, moving_ego=True), args.repeats, lambda: None)
        for device in devices:
            sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
            seeds = iter(range(10_000))
            wall, cpu = _time(lambda: generate_record(preset, seed=next(seeds), moving_ego=True, device=device),
                              args.repeats, sync)
            cpu_rate = (T * V) / (cpu / args.threads) if device == "cpu" else float("nan")
            print(f"{preset.name:7} {preset.camera.H:>3}×{preset.camera.W:<4} {T}×{V:<2} {device:6} {wall:9.3f} "
                  f"{T * V / wall:14.1f} {cpu_rate:23.1f} {scene_wall:17.3f}")


if __name__ == "__main__":
    main()
