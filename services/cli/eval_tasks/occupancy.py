"""`n3dmap eval occupancy`: occupancy accuracy on labelled voxels (the paper's appendix protocol,
core.eval.protocols.occupancy: the map from one view, labels from it and the next view)."""

from __future__ import annotations

from core.device import resolve_device
from core.eval.protocols.occupancy import NEEDS, OccupancyEvalConfig, evaluate
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval
from services.cli.eval_tasks.common import heightmap
from services.cli.eval_tasks.plots import image_grid
from services.reports import Report


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "occupancy", help="occupancy accuracy (occupied/free/all) and IoU")
    parser.add_argument("--input-view", type=int, default=0, help="the single view the map is built from")
    parser.add_argument("--threshold", type=float, default=0.5, help="P(occupied) threshold")
    parser.set_defaults(func=run)


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    result = evaluate(bundle, iter_records(args.data, args.max_records),
                      OccupancyEvalConfig(input_view=args.input_view, threshold=args.threshold), device=device)
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
