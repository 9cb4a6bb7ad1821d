"""`n3dmap eval occupancy`: occupancy accuracy on labelled voxels (the paper's appendix protocol,
core.eval.protocols.occupancy: the map from one view, labels from it and the next view)."""

from __future__ import annotations

from core.device import resolve_device
from pathlib import Path

from core.eval.protocols.occupancy import (
    NEEDS, OccupancyEvalConfig, choose_balanced_threshold, evaluate,
)
from services.cli.errors import CliError
from services.cli.eval import add_eval_parser, check_data_preset, iter_records, load_bundle_for_eval
from services.cli.eval_tasks.common import heightmap
from services.cli.eval_tasks.plots import image_grid
from services.reports import Report


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "occupancy", help="occupancy accuracy (occupied/free/all) and IoU")
    parser.add_argument("--input-view", type=int, default=0, help="the single view the map is built from")
    choice = parser.add_mutually_exclusive_group()
    choice.add_argument("--threshold", type=float, default=None, help="P(occupied) threshold (default 0.5)")
    choice.add_argument("--balanced-on", metavar="DIR", default=None,
                        help="choose the threshold on another dataset (e.g. validation records): the one of 0.05, "
                             "0.10, ..., 0.95 whose worse class accuracy there is highest, each of its views taken "
                             "as the input in turn, as `bench paper` does; then score --data with it")
    parser.set_defaults(func=run)


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    threshold, chosen_on = (0.5 if args.threshold is None else args.threshold), None
    if not 0.0 <= threshold <= 1.0:
        raise CliError(f"--threshold must lie in [0, 1], got {threshold}")
    if args.balanced_on is not None:
        if not Path(args.balanced_on).is_dir():
            raise CliError(f"--balanced-on {args.balanced_on}: not a directory")
        check_data_preset(args.balanced_on, bundle, bundle_path=args.bundle, flag="--balanced-on")
        if Path(args.balanced_on).resolve() == Path(args.data).resolve():
            raise CliError("--balanced-on must name other records than --data (a threshold chosen on the scored "
                           "records flatters them)")
        threshold, on = choose_balanced_threshold(
            bundle, iter_records(args.balanced_on, args.max_records, flag="--balanced-on"), device=device)
        chosen_on = {"data": args.balanced_on, "acc_occupied": on["acc_occupied"], "acc_free": on["acc_free"]}
    result = evaluate(bundle, iter_records(args.data, args.max_records),
                      OccupancyEvalConfig(input_view=args.input_view, threshold=threshold), device=device)
    s = result["scores"]
    report = Report(kind="occupancy", title="Occupancy evaluation", bundle=args.bundle, data=args.data,
                    settings={"max_records": args.max_records, "frames": result["frames"],
                              "input_view": args.input_view, "threshold": threshold, "threshold_chosen_on": chosen_on,
                              "device": str(device)})
    report.metrics = {"occupancy": s}
    report.text("Map from one view; labels from that view and the next one; unlabelled voxels ignored. "
                f"Threshold {threshold:g}" + ("." if chosen_on is None else
                f", the balanced one chosen on {chosen_on['data']} (there: occupied {chosen_on['acc_occupied']:.3f}, "
                f"free {chosen_on['acc_free']:.3f})."))
    report.table(["3D area type", "accuracy"], [["occupied space", s["acc_occupied"]],
                                                ["free space", s["acc_free"]], ["all space", s["acc_all"]]])
    report.text(f"Occupied IoU (within labelled voxels): {s['iou_occupied']:.3f}. Labelled voxels: "
                f"{s['voxels_occupied']} occupied, {s['voxels_free']} free.")
    ex = result["example"]
    report.figure("occupancy_heightmap", image_grid(
        [("input view points", heightmap(ex["input"])), ("predicted occupancy", heightmap(ex["prob"], threshold)),
         ("occupied labels", heightmap(ex["occ"]))], suptitle="Heightmaps (voxels above the grid bottom)"),
        "Heightmaps of the first frame: input, prediction, labels")
    out = report.write(args.out)
    print(f"occupancy: {result['frames']} frames, threshold {threshold:g}"
          f"{'' if chosen_on is None else ' (balanced on ' + chosen_on['data'] + ')'}, acc occupied "
          f"{s['acc_occupied']:.3f} free {s['acc_free']:.3f} all {s['acc_all']:.3f}, IoU {s['iou_occupied']:.3f} "
          f"-> {out / 'report.md'}")
    return 0
