"""How much does a slightly wrong stabilising pose cost the moving-object boxes?

    python tests/benchmarks/bench_pose_sensitivity.py --data DIR --bundle FLOW_BUNDLE [--bundle ...]
        [--egomotion EGO_BUNDLE] [--camera static moving] [--jitter-mrad 0.2] [--jitter-mm 3] [--threads 1]

On the pairs (t, t+1) of DIR's records, per camera setting and per flow bundle, `core.pipeline.
moving_objects` (the size prior estimated per bundle, as `eval moving` does) with three stabilising poses:
- exact: the records' poses;
- jittered: the true ref0_T_ref1 times a random rigid error δ in ref1's frame (rotation up to
  --jitter-mrad about a random axis, translation up to --jitter-mm per axis / √3; seed 0);
- egomotion (with --egomotion): the module's estimate (core.pipeline.estimate_egomotion).
A pose enters as the records' own (core.eval.protocols.inputs.with_stabilising_pose: frame 1's whole rig
moves, so only ref0_T_ref1 changes; offsetting world_T_ref1 alone cancels out and measures nothing).
Prints AP3D at IoU 0.5 / 0.25 and the box count per row, then one JSON line with every figure.

Measured (session 16; 32 held-out small records of data seed 7, 16 static- and 16 moving-camera pairs,
seed 0's bench flow bundle): docs/findings.md, "How this report's verdicts moved".
"""

from __future__ import annotations

import argparse
import json

import torch

from core.bundle import load_bundle
from core.device import resolve_device
from core.data.shards import ShardDataset
from core.eval.method_ap import MethodAP
from core.eval.moving_protocol import camera_setting, gt_moving_boxes
from core.eval.protocols.inputs import pair_inputs, record_batch, with_stabilising_pose
from core.eval.protocols.moving import IOUS, MODEL, method_configs
from core.geometry import se3
from core.geometry.poses import relative
from core.pipeline import estimate_egomotion
from core.pipeline.moving import MovingObjectsConfig, moving_objects


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True)
    p.add_argument("--bundle", required=True, action="append", help="flow bundle (repeatable)")
    p.add_argument("--egomotion", default=None, help="bundle with an egomotion module: its estimate as a row")
    p.add_argument("--camera", nargs="+", choices=("static", "moving"), default=["static", "moving"])
    p.add_argument("--jitter-mrad", type=float, default=0.2)
    p.add_argument("--jitter-mm", type=float, default=3.0)
    p.add_argument("--max-records", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)

    dataset = ShardDataset(args.data)
    count = len(dataset) if args.max_records is None else min(args.max_records, len(dataset))
    records = [dataset[i] for i in range(count)]
    ego = load_bundle(args.egomotion, device) if args.egomotion else None
    rows = ["exact", f"jittered {args.jitter_mrad:g} mrad / {args.jitter_mm:g} mm"] + (["egomotion"] if ego else [])
    results = {}
    for path in args.bundle:
        bundle = load_bundle(path, device)
        grid = bundle.preset.grid
        config = method_configs(bundle, records, device=device, config=MovingObjectsConfig(), size_prior="auto")[MODEL]
        for camera in args.camera:
            acc = {row: MethodAP(IOUS) for row in rows}
            generator = torch.Generator().manual_seed(0)
            pairs = 0
            for record in records:
                batch = record_batch(record, device)
                for t in range(batch["rgb"].shape[1] - 1):
                    if camera_setting(record, t) != camera:
                        continue
                    truth = gt_moving_boxes(record, t, grid, min_points=10)
                    exact = pair_inputs(batch, t, t + 1)
                    true_pose = relative(exact["world_T_ref0"], exact["world_T_ref1"])  # ref0_T_ref1 B×4×4
                    for row in rows:
                        if row == "exact":
                            inputs = exact
                        elif row == "egomotion":
                            with torch.no_grad():
                                inputs = with_stabilising_pose(exact, estimate_egomotion(ego, **exact)["ref0_T_ref1"])
                        else:
                            error = se3.random_rigid(1, args.jitter_mrad * 1e-3, args.jitter_mm * 1e-3 / 3 ** 0.5,
                                                     generator, device=device)
                            inputs = with_stabilising_pose(exact, true_pose @ error)
                        with torch.no_grad():
                            out = moving_objects(bundle, **inputs, config=config)
                        valid = out["valid"][0]
                        acc[row].add_frame(out["boxes"][0][valid].double().cpu().numpy(),
                                           out["scores"][0][valid].double().cpu().numpy(), truth)
                    pairs += 1
            print(f"{path}: {pairs} {camera}-camera pairs")
            for row, a in acc.items():
                s = a.summary()
                results[f"{path}|{camera}|{row}"] = {"ap3d_0.5": s["ap3d"]["0.5"], "ap3d_0.25": s["ap3d"]["0.25"],
                                                     "boxes": s["num_pred"], "true": s["num_gt"], "pairs": pairs}
                print(f"  {row:28s} AP3D@0.5 {s['ap3d']['0.5']:.3f}  @0.25 {s['ap3d']['0.25']:.3f}  "
                      f"boxes {s['num_pred']} for {s['num_gt']} true movers", flush=True)
    print(json.dumps(results))


if __name__ == "__main__":
    main()
