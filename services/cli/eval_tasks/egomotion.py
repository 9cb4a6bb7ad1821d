"""`n3dmap eval egomotion`: relative pose error of the bundle's egomotion vs ICP and identity baselines.

Each record contributes its consecutive pairs (t, t+1) (a record with one step pairs it with itself).
Errors are TUM RPE on ref0_T_ref1 (core.eval.egomotion_metrics). ICP (point-to-plane) aligns the two
frames' depth points inside the map grid (the region the module sees), downsampled to half a voxel.
`--perturb-deg/--perturb-m` move the second frame's map frame by a seeded yaw-heavy random rigid
transform (as egomotion training augments), for datasets whose camera does not move.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from core.baselines.icp import icp_point_to_plane, voxel_downsample
from core.eval.egomotion_metrics import relative_pose_errors, summarize_errors
from core.geometry import se3
from core.pipeline.egomotion import estimate_egomotion
from core.tasks.egomotion import random_perturbation
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval, resolve_device
from services.cli.eval_tasks.common import pair_inputs, record_batch
from services.cli.eval_tasks.plots import histograms
from services.reports import Report


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "egomotion", help="egomotion error (rad, deg, m) vs ICP and identity")
    parser.add_argument("--perturb-deg", type=float, default=0.0,
                        help="add a random yaw-heavy rotation up to this many degrees to every pair")
    parser.add_argument("--perturb-m", type=float, default=0.0, help="and a random translation up to this (m)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the perturbations")
    parser.add_argument("--no-icp", action="store_true", help="skip the ICP baseline")
    parser.set_defaults(func=run)


def _cloud(record: dict, t: int, ref_T_refp: np.ndarray, grid) -> np.ndarray:
    """Depth points of step t in the (perturbed) map frame, inside the grid, downsampled: N×3."""
    from core.data.ground_truth import points_in_ref

    xyz, valid = points_in_ref(record, t)  # V×N×3, V×N
    xyz = xyz[valid].double().numpy()
    refp_T_ref = np.linalg.inv(ref_T_refp)
    xyz = xyz @ refp_T_ref[:3, :3].T + refp_T_ref[:3, 3]
    lo, hi = np.array(grid.bounds_min), np.array(grid.bounds_max)
    xyz = xyz[((xyz >= lo) & (xyz < hi)).all(axis=1)]
    return voxel_downsample(xyz, grid.voxel_size / 2)


def evaluate(bundle, records, *, device, perturb_deg: float, perturb_m: float, seed: int, icp: bool) -> dict:
    grid = bundle.preset.grid
    gen = torch.Generator().manual_seed(seed)
    est, gts, icps = [], [], []
    for record in records:
        batch = record_batch(record, device)
        T = batch["rgb"].shape[1]
        for t0 in range(max(T - 1, 1)):
            t1 = min(t0 + 1, T - 1)
            P = (random_perturbation(1, max_deg=perturb_deg, max_m=perturb_m, generator=gen)
                 if perturb_deg > 0 or perturb_m > 0 else torch.eye(4)[None])  # ref1_T_ref1'
            inputs = pair_inputs(batch, t0, t1)
            inputs["world_T_ref1"] = inputs["world_T_ref1"] @ P.to(device)
            out = estimate_egomotion(bundle, **inputs)
            gt = se3.invert(inputs["world_T_ref0"].double()) @ inputs["world_T_ref1"].double()
            est.append(out["ref0_T_ref1"].double().cpu())
            gts.append(gt.cpu())
            if icp:
                source = _cloud(record, t1, P[0].double().numpy(), grid)
                target = _cloud(record, t0, np.eye(4), grid)
                res = icp_point_to_plane(source, target, iterations=30, max_distance=max(1.0, 2 * grid.voxel_size))
                icps.append(torch.from_numpy(res.target_T_source)[None])
    est, gts = torch.cat(est), torch.cat(gts)
    methods = {"model": relative_pose_errors(est, gts),
               "identity": relative_pose_errors(torch.eye(4, dtype=torch.float64).expand_as(gts), gts)}
    if icp:
        methods["icp"] = relative_pose_errors(torch.cat(icps), gts)
    gt_motion = {"rot_deg": se3.rotation_angle(gts[:, :3, :3]) * 180 / math.pi, "trans_m": gts[:, :3, 3].norm(dim=1)}
    return {"methods": methods, "gt_motion": gt_motion}


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, ("egomotion",), data_dir=args.data)
    result = evaluate(bundle, iter_records(args.data, args.max_records), device=device,
                      perturb_deg=args.perturb_deg, perturb_m=args.perturb_m, seed=args.seed, icp=not args.no_icp)
    report = Report(kind="egomotion", title="Egomotion evaluation", bundle=args.bundle, data=args.data,
                    settings={"max_records": args.max_records, "perturb_deg": args.perturb_deg,
                              "perturb_m": args.perturb_m, "seed": args.seed, "device": str(device)})
    summaries = {name: summarize_errors(errs) for name, errs in result["methods"].items()}
    report.metrics = {"egomotion": summaries,
                      "gt_motion": {k: float(v.mean()) for k, v in result["gt_motion"].items()}}
    pairs = summaries["model"]["pairs"]
    report.text(f"{pairs} frame pairs. Relative pose error err = inv(gt)·est of ref0_T_ref1 (TUM RPE): "
                "rotation = angle of err, translation = ‖t of err‖. Mean ground-truth motion per pair: "
                f"{report.metrics['gt_motion']['rot_deg']:.2f}° and {report.metrics['gt_motion']['trans_m']:.3f} m.")
    report.heading("Errors (mean / median)")
    report.table(["method", "R (rad)", "R (deg)", "t (m)", "R median (deg)", "t median (m)"],
                 [[name, s["rot_err_rad_mean"], s["rot_err_deg_mean"], s["trans_err_m_mean"],
                   s["rot_err_deg_median"], s["trans_err_m_median"]] for name, s in summaries.items()], digits=4)
    report.figure("rotation_error_hist", histograms(
        {n: e["rot_err_deg"].numpy() for n, e in result["methods"].items()}, xlabel="rotation error (deg)",
        title="Rotation error per pair"), "Rotation error per pair")
    report.figure("translation_error_hist", histograms(
        {n: e["trans_err_m"].numpy() for n, e in result["methods"].items()}, xlabel="translation error (m)",
        title="Translation error per pair"), "Translation error per pair")
    out = report.write(args.out)
    s = summaries["model"]
    print(f"egomotion: {pairs} pairs, R {s['rot_err_deg_mean']:.3f}°, t {s['trans_err_m_mean']:.3f} m "
          f"-> {out / 'report.md'}")
    return 0
