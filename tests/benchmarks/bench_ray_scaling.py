"""Ray Train scaling: pretraining samples/s with 1 vs 2 Ray workers (tiny preset by default).

    python tests/benchmarks/bench_ray_scaling.py [--objective contrastive] [--steps 12] [--data DIR]

Each configuration is a fresh `run_training` (embedded local Ray, DDP, Ray Data streaming the shards).
Throughput is measured from the rank-0 metrics.jsonl timestamps over the steps after `--warmup`
(so Ray/actor start-up is excluded; it is printed separately as wall time). Samples per step =
workers × batch size. Prints one line per worker count and the 2-vs-1 speed-up.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("RAY_AUTH_MODE", "disabled")


def make_dataset(out: Path, *, preset_name: str, records: int) -> Path:
    from core.data.shards import write_dataset
    from core.presets import get_preset
    from core.synthetic import generate_record

    preset = get_preset(preset_name)
    write_dataset(out, (generate_record(preset, seed=i) for i in range(records)), split="train",
                  preset_name=preset_name, grid=preset.grid.to_dict(), generator={"source": "synthetic"},
                  seed=0, shard_bytes=4 << 20)
    return out


def measure(data: Path, run_dir: Path, *, workers: int, args) -> dict:
    from services.training.config import TrainJobConfig
    from services.training.job import run_training
    from services.training.progress import read_metrics

    config = TrainJobConfig(task="pretrain", task_options={"objective": args.objective}, data_dir=str(data),
                            run_dir=str(run_dir), preset=args.preset, workers=workers, steps=args.steps,
                            batch_size=args.batch_size, checkpoint_every=args.steps, log_every=1,
                            object_store_mb=200, device="cpu")
    started = time.monotonic()
    run_training(config)
    wall = time.monotonic() - started
    records = [r for r in read_metrics(run_dir / "metrics.jsonl") if r["step"] > args.warmup]
    first, last = records[0], records[-1]
    seconds = last["time"] - first["time"]
    steps = last["step"] - first["step"]
    samples = steps * workers * args.batch_size
    return {"workers": workers, "samples_per_s": samples / seconds, "s_per_step": seconds / steps,
            "wall_s": wall}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--objective", choices=("contrastive", "regression"), default="contrastive")
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=1, help="per worker")
    parser.add_argument("--data", default=None, help="dataset dir (default: generate 8 records)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench_ray_") as tmp:
        tmp = Path(tmp)
        data = Path(args.data) if args.data else make_dataset(tmp / "data", preset_name=args.preset, records=8)
        print(f"preset {args.preset}, objective {args.objective}, {args.steps} steps, batch {args.batch_size}"
              f"/worker, cpus {os.cpu_count()}, load {os.getloadavg()[0]:.1f}")
        results = []
        for workers in (1, 2):
            r = measure(data, tmp / f"run{workers}", workers=workers, args=args)
            results.append(r)
            print(f"workers {workers}: {r['samples_per_s']:.2f} samples/s  {r['s_per_step']:.3f} s/step  "
                  f"(wall incl. Ray start-up {r['wall_s']:.1f} s)", flush=True)
        print(f"speed-up 2 vs 1 workers: {results[1]['samples_per_s'] / results[0]['samples_per_s']:.2f}×")


if __name__ == "__main__":
    main()
