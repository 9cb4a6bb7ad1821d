"""Detector timings: one training step (frozen and fine-tuned features) and detect() inference.

    python tests/benchmarks/bench_detector.py [--preset tiny] [--batch 2] [--device cpu] [--threads 1]

Target: tiny preset, batch 2, CPU: < 1 s per training step. Prints figures; not a test.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from core.bundle import Bundle  # noqa: E402
from core.data.batch import records_to_batch  # noqa: E402
from core.pipeline.detect import detect  # noqa: E402
from core.presets import get_preset  # noqa: E402
from core.synthetic import generate_record  # noqa: E402
from core.tasks.detector import DetectorTask  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _time_steps(task: DetectorTask, batch: dict, device: torch.device, repeats: int) -> float:
    opt = torch.optim.Adam([p for p in task.parameters() if p.requires_grad], lr=1e-3)
    task.train()

    def step() -> None:
        out = task(batch)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()

    step()  # warm-up
    _sync(device)
    start = time.perf_counter()
    for _ in range(repeats):
        step()
    _sync(device)
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    preset = get_preset(args.preset)

    records = [generate_record(preset, seed=s) for s in range(args.batch)]
    batch = records_to_batch(records, device)
    print(f"preset {preset.name}: grid Z×Y×X {preset.grid.shape_zyx}, {batch['rgb'].shape[2]} views, "
          f"batch {args.batch}, device {device}, threads {args.threads}")
    for freeze in (True, False):
        task = DetectorTask.from_preset(preset, freeze_features=freeze, seed=0).to(device)
        seconds = _time_steps(task, batch, device, args.repeats)
        n_anchors = task.detector.anchors.shape[0]
        print(f"train step ({'frozen' if freeze else 'fine-tuned'} features): {seconds:.3f} s  "
              f"[{n_anchors} anchors, stride {task.cfg.stride}]")

    task.eval()
    bundle = Bundle(preset=preset, modules=task.exported_modules())
    args_detect = (batch["rgb"][:, 0], batch["depth"][:, 0], batch["pix_T_cam"], batch["world_T_cam"][:, 0],
                   batch["world_T_ref"][:, 0])
    detect(bundle, *args_detect)  # warm-up
    _sync(device)
    start = time.perf_counter()
    for _ in range(args.repeats):
        detect(bundle, *args_detect)
    _sync(device)
    print(f"detect() inference: {(time.perf_counter() - start) / args.repeats:.3f} s per batch of {args.batch}")


if __name__ == "__main__":
    main()
