"""The egomotion module's last, weightless stage alone (core/models/egomotion_fine.py) against point-to-plane ICP.

    python tests/benchmarks/bench_egomotion_fine.py --data DIR [--preset small] [--stages tsdf:4 splat:2]
        [--pairs 32] [--start-deg 0.57 --start-m 0.25] [--threads 1]

On the moving-camera pairs (t = 0 → 1) of DIR, as the paper bench's egomotion row picks them, each stage
`KIND:FACTOR` starts from the true ref0_T_ref1 moved by a fixed yaw of --start-deg and a translation of
--start-m (what the module's learned stages would hand over, only farther: they end ~0.03 m off) and aligns
the two frames; ICP runs as core.eval.protocols.egomotion runs it (from the identity, shrinking gate). Prints
per stage the mean / median rotation (rad) and translation (m) errors, their ratio to ICP's means, and the
median seconds per pair (the frames' fine data and the alignment, one thread by default), with the load
average. No model is needed: the stage has no weights.

Measured (docs/findings.md, "Egomotion"; the small report's data/test, 32 pairs, load ~4.5): tsdf:4
0.00014 rad / 0.0026 m against ICP's 0.00014 / 0.0028 (0.99 × / 0.95 ×).
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import torch

from core.baselines.icp import icp_coarse_to_fine
from core.data.ground_truth import gt_egomotion
from core.data.shards import ShardDataset
from core.eval.moving_protocol import camera_setting
from core.eval.protocols.egomotion import _cloud, icp_gates
from core.eval.protocols.inputs import pair_inputs, record_batch
from core.geometry import se3
from core.geometry.poses import rig_cam_T_ref
from core.models.egomotion_fine import FineAlignment, align_fine, fine_frame, fine_grid
from core.presets import get_preset


def pose_error(estimate: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """(rotation angle rad, translation m) of inv(truth)·estimate; both 4×4 float64."""
    delta = torch.linalg.inv(truth) @ estimate
    return float(se3.rotation_angle(delta[None, :3, :3])[0]), float(delta[:3, 3].norm())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="a dataset directory (its moving-camera pairs are used)")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--stages", nargs="+", default=["tsdf:4", "splat:2"], help="KIND:FACTOR, e.g. tsdf:4")
    parser.add_argument("--pairs", type=int, default=32)
    parser.add_argument("--start-deg", type=float, default=0.57, help="start: the truth turned by this yaw")
    parser.add_argument("--start-m", type=float, default=0.25, help="and moved by this distance (x and z)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    grid = get_preset(args.preset).grid
    stages = []
    for spec in args.stages:
        kind, _, factor = spec.partition(":")
        stages.append((spec, FineAlignment(kind=kind, factor=int(factor or 2))))
    yaw = math.radians(args.start_deg)
    off = args.start_m / math.sqrt(2.0)
    start_T_truth = se3.from_rt(se3.axis_angle_to_matrix(torch.tensor([[0.0, yaw, 0.0]], dtype=torch.float64)),
                                torch.tensor([[off, 0.0, -off]], dtype=torch.float64))[0]
    dataset = ShardDataset(args.data)
    errors = {spec: [] for spec, _ in stages} | {"icp": []}
    seconds = {spec: [] for spec, _ in stages}
    for i in range(len(dataset)):
        record = dataset[i]
        if record["rgb"].shape[0] < 2 or camera_setting(record, 0) != "moving":
            continue
        truth = gt_egomotion(record, 0, 1)["ref0_T_ref1"].double()
        inputs = pair_inputs(record_batch(record, "cpu"), 0, 1)
        cam0 = rig_cam_T_ref(inputs["world_T_cam0"], inputs["world_T_ref0"])  # 1×V×4×4
        cam1 = rig_cam_T_ref(inputs["world_T_cam1"], inputs["world_T_ref1"])
        for spec, config in stages:
            began = time.perf_counter()
            frame0 = fine_frame(inputs["depth0"], inputs["pix_T_cam0"], cam0, grid, config)
            frame1 = fine_frame(inputs["depth1"], inputs["pix_T_cam1"], cam1, grid, config)
            start = (start_T_truth @ truth).float()[None]  # 1×4×4
            estimate = align_fine(start, frame0, frame1, fine_grid(grid, config.factor), config)[0].double()
            seconds[spec].append(time.perf_counter() - began)
            errors[spec].append(pose_error(estimate, truth))
        source, target = _cloud(record, 1, np.eye(4), grid), _cloud(record, 0, np.eye(4), grid)
        icp = icp_coarse_to_fine(source, target, iterations=30, max_distances=icp_gates(grid.voxel_size))
        errors["icp"].append(pose_error(torch.from_numpy(icp.target_T_source), truth))
        if len(errors["icp"]) >= args.pairs:
            break
    if not errors["icp"]:
        raise SystemExit(f"{args.data}: no moving-camera pairs")
    icp = np.array(errors["icp"])
    print(f"{len(icp)} moving-camera pairs of {args.data}; start {args.start_deg}° / {args.start_m} m off the truth; "
          f"{args.threads} thread(s), load {os.getloadavg()[0]:.1f}")
    print(f"{'stage':10s} {'R mean':>9s} {'t mean':>8s} {'R median':>9s} {'t median':>9s} {'x ICP (R / t)':>14s} {'s/pair':>7s}")
    for name, rows in errors.items():
        a = np.array(rows)
        ratio = "" if name == "icp" else f"{a[:, 0].mean() / icp[:, 0].mean():.2f} / {a[:, 1].mean() / icp[:, 1].mean():.2f}"
        secs = "" if name == "icp" else f"{np.median(seconds[name]):.2f}"
        print(f"{name:10s} {a[:, 0].mean():9.5f} {a[:, 1].mean():8.4f} {np.median(a[:, 0]):9.5f} "
              f"{np.median(a[:, 1]):9.4f} {ratio:>14s} {secs:>7s}")


if __name__ == "__main__":
    main()
