"""Geometry timings at the PAPER preset's grid and image size (prints figures; not a test).

    python tests/benchmarks/bench_geometry.py [--device cpu|cuda] [--threads 1]
"""

from __future__ import annotations

import argparse
import time

import torch

from core.geometry import camera, se3
from core.geometry.freespace import free_space
from core.geometry.frustum import frustum_resample
from core.geometry.grid import GridConfig
from core.geometry.resample import warp_flow, warp_rigid
from core.geometry.unproject import unproject_image
from core.geometry.voxelize import voxelize


def _time(fn, device: torch.device, repeats: int = 3) -> float:
    fn()  # warm-up
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    B, H, W, C = args.batch, 128, 384, 32
    grid = GridConfig(xmin=-16.0, xmax=16.0, ymin=-4.0, ymax=4.0, zmin=0.0, zmax=32.0, Z=128, Y=32, X=128)
    g = torch.Generator().manual_seed(0)
    K = camera.intrinsics_from_fov(H, W, 70.0).expand(B, 4, 4).to(device)
    cam_T_ref = se3.random_rigid(B, 0.1, 0.5, g).to(device)
    depth = (torch.rand(B, H, W, generator=g) * 30 + 1).to(device)
    xyz_cam, valid = camera.depth_to_points(depth, K)
    xyz_ref = se3.apply(se3.invert(cam_T_ref), xyz_cam)
    feat = torch.randn(B, C, *grid.shape_zyx, generator=g).to(device)
    rgb = torch.rand(B, 3, H, W, generator=g).to(device)
    flow = torch.randn(B, 3, *grid.shape_zyx, generator=g).to(device)
    rows = {
        "voxelize (N=49152)": lambda: voxelize(xyz_ref, grid, valid),
        "unproject_image (C=3)": lambda: unproject_image(rgb, K, cam_T_ref, grid),
        f"warp_rigid (C={C})": lambda: warp_rigid(feat, cam_T_ref, grid),
        f"warp_flow (C={C})": lambda: warp_flow(feat, flow),
        f"frustum_resample (C={C}, D=32, 64×192)": lambda: frustum_resample(
            feat, camera.scale_intrinsics(K, 0.5, 0.5), cam_T_ref, grid, 64, 192, 32, 1.0, 40.0),
        "free_space (N=49152)": lambda: free_space(xyz_cam, valid, cam_T_ref, grid),
    }
    print(f"device={device} threads={args.threads} B={B} grid=128×32×128 image={H}×{W}")
    for name, fn in rows.items():
        print(f"{name:45s} {1000 * _time(fn, device):9.1f} ms")


if __name__ == "__main__":
    main()
