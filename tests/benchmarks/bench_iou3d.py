"""Time exact oriented 3D IoU (core.eval.iou3d) on CPU: pairwise N×M for scene-like and dense layouts.

Run: python tests/benchmarks/bench_iou3d.py [N]
Prints wall time per call and pairs per second. Scene-like: boxes spread over a 64 m × 64 m area
(most pairs skipped by the circumcircle test); dense: all boxes within a few metres (every pair clipped).
"""

import sys
import time

import numpy as np

from core.eval.iou3d import iou_3d


def boxes(n, spread, rng):
    return np.concatenate([rng.uniform(-spread, spread, (n, 1)), rng.uniform(-0.5, 0.5, (n, 1)),
                           rng.uniform(-spread, spread, (n, 1)), rng.uniform(1, 5, (n, 3)),
                           rng.uniform(-np.pi, np.pi, (n, 1))], axis=1)


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 500
    rng = np.random.default_rng(0)
    for name, spread in (("scene-like (±32 m)", 32.0), ("dense (±2 m)", 2.0)):
        a, b = boxes(n, spread, rng), boxes(n, spread, rng)
        iou_3d(a[:10], b[:10])  # warm up
        t0 = time.perf_counter()
        iou_3d(a, b)
        dt = time.perf_counter() - t0
        print(f"{name}: {n}×{n} pairs in {dt * 1e3:.1f} ms ({n * n / dt / 1e6:.2f} M pairs/s)")


if __name__ == "__main__":
    main()
