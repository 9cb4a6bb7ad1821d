"""`n3dmap eval occupancy`: occupancy accuracy on labelled voxels (the paper's appendix protocol).

Per record and step t: the map is built from ONE view (`--input-view`), and the labels are the union of
that view's and the next view's (occupied = voxelised points, free = ray traversal; unlabelled voxels
are ignored). Scores: accuracy for occupied / free / all labelled voxels and occupied IoU (definitions:
core.eval.occupancy_metrics).
"""

from __future__ import annotations

import numpy as np
import torch

from core.data.ground_truth import gt_free, gt_occupancy
from core.eval.occupancy_metrics import add_counts, occupancy_counts, occupancy_scores
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval, resolve_device
from services.cli.eval_tasks.common import heightmap, record_batch
from services.cli.eval_tasks.plots import image_grid
from services.reports import Report


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "occupancy", help="occupancy accuracy (occupied/free/all) and IoU")
    parser.add_argument("--input-view", type=int, default=0, help="the single view the map is built from")
    parser.add_argument("--threshold", type=float, default=0.5, help="P(occupied) threshold")
    parser.set_defaults(func=run)


@torch.no_grad()
def evaluate(bundle, records, *, device, input_view: int, threshold: float) -> dict:
    from core.tasks.poses import cam_T_ref
    from services.cli.main import CliError

    grid = bundle.preset.grid
    mapper, head = bundle.modules["mapper"], bundle.modules["occupancy"]
    counts: dict = {}
    example = None
    frames = 0
    for record in records:
        batch = record_batch(record, device)
        T, V = batch["rgb"].shape[1:3]
        if not 0 <= input_view < V:
            raise CliError(f"--input-view {input_view}: records have {V} views")
        label_views = sorted({input_view, (input_view + 1) % V})
        v = [input_view]
        for t in range(T):
            cam = cam_T_ref(batch, t, t)  # 1×V×4×4
            features = mapper(batch["rgb"][:, t][:, v], batch["depth"][:, t][:, v], batch["pix_T_cam"][:, v], cam[:, v])
            prob = head.probabilities(features)  # 1×1×Z×Y×X
            occ = gt_occupancy(record, t, grid, label_views)[None].to(device) > 0.5
            free = gt_free(record, t, grid, label_views)[None].to(device) > 0.5
            counts = add_counts(counts, occupancy_counts(prob, occ, free, threshold=threshold))
            frames += 1
            if example is None:
                example = {"prob": prob[0, 0].cpu().numpy(), "occ": occ[0, 0].cpu().numpy().astype(np.float32),
                           "input": gt_occupancy(record, t, grid, v)[0].numpy()}
    return {"scores": occupancy_scores(counts), "frames": frames, "example": example}


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, ("mapper", "occupancy"), data_dir=args.data)
    result = evaluate(bundle, iter_records(args.data, args.max_records), device=device,
                      input_view=args.input_view, threshold=args.threshold)
    s = result["scores"]
    report = Report(kind="occupancy", title="Occupancy evaluation", bundle=args.bundle, data=args.data,
                    settings={"max_records": args.max_records, "frames": result["frames"],
                              "input_view": args.input_view, "threshold": args.threshold, "device": str(device)})
    report.metrics = {"occupancy": s}
    report.text("Map from one view; labels from that view and the next one; unlabelled voxels ignored.")
    report.table(["3D area type", "accuracy"], [["occupied space", s["acc_occupied"]],
                                                ["free space", s["acc_free"]], ["all space", s["acc_all"]]])
    report.text(f"Occupied IoU (within labelled voxels): {s['iou_occupied']:.3f}. Labelled voxels: "
                f"{s['voxels_occupied']} occupied, {s['voxels_free']} free.")
    ex = result["example"]
    report.figure("occupancy_heightmap", image_grid(
        [("input view points", heightmap(ex["input"])), ("predicted occupancy", heightmap(ex["prob"], args.threshold)),
         ("occupied labels", heightmap(ex["occ"]))], suptitle="Heightmaps (voxels above the grid bottom)"),
        "Heightmaps of the first frame: input, prediction, labels")
    out = report.write(args.out)
    print(f"occupancy: {result['frames']} frames, acc occupied {s['acc_occupied']:.3f} free {s['acc_free']:.3f} "
          f"all {s['acc_all']:.3f}, IoU {s['iou_occupied']:.3f} -> {out / 'report.md'}")
    return 0
