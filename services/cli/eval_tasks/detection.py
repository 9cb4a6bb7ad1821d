"""`n3dmap eval detection`: 3D detection AP, in two modes.

- Files: `--pred DIR --gt DIR --out REPORT_DIR [--iou T ...] [--classes C ...]` scores KITTI-format
  label files (core.eval.protocols.label_files, written by services.cli.eval_detection); metrics.json
  holds `detection.<class>.ap3d` / `.apbev` at the top level, as that writer documents.
- Dataset: `--data DIR --bundle B --out REPORT_DIR` runs the bundle's detector on the map of every time
  step of every record and scores it against the record's axis-aligned boxes in ref_t
  (core.eval.protocols.detection). All-point AP at 3D and BEV IoU 0.33 / 0.5 / 0.75 (+ any `--iou`),
  in metrics.json under `metrics.detection.object`.
"""

from __future__ import annotations

import argparse

from core.device import resolve_device
from core.eval.protocols.detection import CLASS, NEEDS, evaluate
from core.eval.thresholds import DEFAULT_IOUS, iou_thresholds, threshold_key
from services.cli.argtypes import positive_int
from services.cli.eval import (add_rerun_option, check_rerun_option, iter_records, load_bundle_for_eval,
                               open_rerun_option, print_rerun_option)
from services.cli.eval_detection import run_detection_files_eval
from services.cli.eval_tasks.boxes_report import bev_boxes_figure, pr_figure
from services.reports import Report
from services.viz.rerun_paths import FRAME


def register(kinds) -> None:
    parser = kinds.add_parser(
        "detection", help="3D detection AP (KITTI label files, or a bundle's detector on a dataset)",
        description="Score 3D detections: either KITTI label files (--pred DIR --gt DIR) or the bundle's "
                    "detector on a dataset (--data DIR --bundle B). Writes REPORT_DIR/report.md, "
                    "metrics.json and PR-curve PNGs.")
    files = parser.add_argument_group("KITTI label files")
    files.add_argument("--pred", metavar="DIR", help="predicted <frame>.txt files (with a score column)")
    files.add_argument("--gt", metavar="DIR", help="ground-truth <frame>.txt files")
    files.add_argument("--classes", nargs="+", metavar="C", help="classes to score (default: all in --gt)")
    data = parser.add_argument_group("bundle on a dataset")
    data.add_argument("--data", metavar="DIR", help="dataset directory (manifest.json + shards)")
    data.add_argument("--bundle", metavar="DIR", help="model bundle with 'mapper' and 'detector' modules")
    data.add_argument("--max-records", type=positive_int, default=None, metavar="N",
                      help="evaluate only the first N records (default: all)")
    data.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default: auto)")
    add_rerun_option(data)
    parser.add_argument("--out", required=True, metavar="REPORT_DIR", help="where the report goes (created)")
    parser.add_argument("--iou", nargs="+", type=float, default=[], metavar="T",
                        help=f"IoU thresholds besides {', '.join(map(str, DEFAULT_IOUS))}")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from services.cli.main import CliError

    files_mode = args.pred is not None or args.gt is not None
    data_mode = args.data is not None or args.bundle is not None
    if files_mode and data_mode:
        raise CliError("give either --pred/--gt (label files) or --data/--bundle (a dataset), not both")
    if files_mode:
        if args.rerun is not None:
            raise CliError("--rerun records the bundle's detections on a dataset: give --data/--bundle, not --pred/--gt")
        for flag, value in (("--pred", args.pred), ("--gt", args.gt)):
            if value is None:
                raise CliError(f"label-file mode needs {flag} DIR")
        import os
        for flag, value in (("--pred", args.pred), ("--gt", args.gt)):
            if not os.path.isdir(value):
                raise CliError(f"{flag} {value}: not a directory")
        metrics = run_detection_files_eval(args.pred, args.gt, args.out, ious=args.iou, classes=args.classes)
        for name, e in metrics["detection"].items():
            ap = e["ap3d"]
            print(f"detection {name}: {e['num_gt']} gt, {e['num_pred']} pred, AP3D "
                  + " ".join(f"@{k} {'n/a' if v is None else f'{v:.3f}'}" for k, v in ap.items()))
        print(f"-> {os.path.join(args.out, 'report.md')}")
        return 0
    if args.data is None or args.bundle is None:
        raise CliError("give --pred DIR --gt DIR (label files) or --data DIR --bundle B (a dataset)")
    if args.classes:
        raise CliError("--classes applies to label files only (the bundle's detector is class-agnostic)")
    from services.viz.rerun_eval import close_eval_recorder

    check_rerun_option(args)
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    recorder = open_rerun_option(args, bundle, timeline=FRAME, kind="detection")
    try:
        report = build_report(bundle, iter_records(args.data, args.max_records), device=device, ious=args.iou,
                              bundle_path=args.bundle, data_path=args.data, max_records=args.max_records,
                              recorder=recorder)
    finally:
        close_eval_recorder(recorder)
    out = report.write(args.out)
    e = report.metrics["detection"][CLASS]
    print(f"detection: {report.settings['frames']} frames, {e['num_gt']} gt boxes, {e['num_pred']} detections, "
          + ", ".join(f"AP3D@{k} {_fmt(v)}" for k, v in e["ap3d"].items()) + f" -> {out / 'report.md'}")
    print_rerun_option(args, recorder)
    return 0


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def build_report(bundle, records, *, device, ious=(), bundle_path=None, data_path=None, max_records=None,
                 recorder=None) -> Report:
    thresholds = iou_thresholds(ious)
    result = evaluate(bundle, records, device=device, thresholds=thresholds, recorder=recorder)
    summary = result["ap"].summary()
    report = Report(kind="detection", title="3D object detection evaluation", bundle=bundle_path, data=data_path,
                    settings={"max_records": max_records, "frames": result["frames"], "device": str(device),
                              "iou_thresholds": ", ".join(threshold_key(t) for t in thresholds)})
    report.metrics = {"detection": {CLASS: summary}}
    report.text("The bundle's detector on the map of every time step (all views, known poses), against the "
                "record's boxes in ref_t whose centre lies in the grid, as axis-aligned boxes. All-point "
                "interpolated AP (VOC); a detection matches an unmatched ground-truth box with IoU ≥ the "
                "threshold, highest score first, each ground-truth box at most once.")
    keys = [threshold_key(t) for t in thresholds]
    report.table(["class", *[f"AP3D@{k}" for k in keys], *[f"APBEV@{k}" for k in keys], "GT boxes", "detections"],
                 [["object", *[summary["ap3d"][k] for k in keys], *[summary["apbev"][k] for k in keys],
                   summary["num_gt"], summary["num_pred"]]])
    report.figure("detection_pr", pr_figure({f"3D IoU {k}": result["ap"].curve(t) for t, k in zip(thresholds, keys)},
                                            title="Detection precision–recall (3D IoU)"),
                  "Precision–recall of the detector at each 3D IoU threshold")
    if result["example"] is not None:
        gt, pred = result["example"]
        report.figure("detection_bev", bev_boxes_figure(bundle.preset.grid, [("first frame", None, gt, pred)]),
                      "Bird's-eye view of the first frame: ground truth (green), top-10 detections (red)")
    return report
