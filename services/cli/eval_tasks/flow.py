"""`n3dmap eval flow`: 3D imagination flow error in egomotion-stabilised scenes (the paper's protocol,
core.eval.protocols.flow: the model, its raw flow and the zero-motion baseline; L1 EPE full/static/moving
and the scene-flow scores on occupied voxels).
"""

from __future__ import annotations

import numpy as np
import torch

from core.device import resolve_device
from core.eval.protocols.flow import NEEDS, evaluate
from services.cli.eval import (add_eval_parser, add_rerun_option, check_rerun_option, iter_records,
                               load_bundle_for_eval, open_rerun_option, print_rerun_option)
from services.cli.eval_tasks.plots import image_grid
from services.reports import Report
from services.viz.rerun_paths import PAIR


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "flow", help="3D flow EPE (full/static/moving) vs the zero-motion baseline")
    parser.add_argument("--moving-threshold", type=float, default=1e-3,
                        help="ground-truth flow norm (voxels) above which a voxel counts as moving")
    add_rerun_option(parser)
    parser.set_defaults(func=run)


def _bev(flow: torch.Tensor) -> np.ndarray:
    """3×Z×Y×X -> Z×X largest flow magnitude along the vertical axis (voxels)."""
    return flow.norm(dim=0).amax(dim=1).numpy()


def run(args) -> int:
    from services.viz.rerun_eval import close_eval_recorder

    check_rerun_option(args)
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    recorder = open_rerun_option(args, bundle, timeline=PAIR, kind="flow")
    try:
        result = evaluate(bundle, iter_records(args.data, args.max_records), device=device,
                          moving_threshold=args.moving_threshold, recorder=recorder)
    finally:
        close_eval_recorder(recorder)
    scores = result["scores"]
    report = Report(kind="flow", title="3D imagination flow evaluation", bundle=args.bundle, data=args.data,
                    settings={"max_records": args.max_records, "pairs": result["pairs"],
                              "moving_threshold_voxels": args.moving_threshold, "device": str(device),
                              "occupancy_masking": "occupancy" in bundle.modules})
    report.metrics = {"flow": scores}
    report.text("Mean L1 endpoint error in voxels (Σ over x, y, z of |pred − gt|), egomotion-stabilised with "
                "the record poses; `moving` = voxels whose true flow exceeds the threshold. Rows: `model` zeroes "
                "the flow of voxels the occupancy head calls free (the paper's rule), `model_filled` keeps it "
                "within one voxel of a moving occupied voxel (an object's unseen inside), `model_raw` gates "
                "nothing.")
    report.table(["method", "full", "static", "moving"],
                 [[row, s["epe_l1_full"], s["epe_l1_static"], s["epe_l1_moving"]] for row, s in scores.items()])
    report.heading("Scene-flow scores on occupied voxels")
    report.text("EPE3D: mean L2 error (voxels). Acc3DS: EPE < 0.5 voxel or relative error < 5%. "
                "Acc3DR: EPE < 1 voxel or relative error < 10%. Outliers: EPE > 1.2 voxel or relative error "
                "> 10% (relative tests only where the true flow is non-zero).")
    report.table(["method", "EPE3D", "Acc3DS", "Acc3DR", "outliers"],
                 [[row, s["epe3d"], s["acc3ds"], s["acc3dr"], s["outliers"]] for row, s in scores.items()])
    z = scores["zero_motion"]
    report.text(f"Voxels: {z['voxels_full']} in all, {z['voxels_moving']} moving, {z['voxels_occupied']} occupied.")
    ex = result["example"]
    vmax = float(max(_bev(ex["gt"]).max(), 1e-6))
    report.figure("flow_bev", image_grid([("true |flow|", _bev(ex["gt"])), ("predicted |flow|", _bev(ex["pred"])),
                                          ("|error|", _bev(ex["pred"] - ex["gt"]))], vmin=0.0, vmax=vmax,
                                         suptitle="Bird's-eye view: max over height (voxels)"),
                  "Bird's-eye flow magnitude of the pair with the most moving voxels")
    out = report.write(args.out)
    m = scores["model"]
    print(f"flow: {result['pairs']} pairs, L1 EPE full {m['epe_l1_full']:.3f} static {m['epe_l1_static']:.3f} "
          f"moving {m['epe_l1_moving']:.3f} (zero-motion moving {z['epe_l1_moving']:.3f}) -> {out / 'report.md'}")
    print_rerun_option(args, recorder)
    return 0
