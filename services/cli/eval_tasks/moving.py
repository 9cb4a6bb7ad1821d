"""`n3dmap eval moving`: unsupervised moving-object detection, PR curves and AP (paper §5).

The protocol is core.eval.protocols.moving: every consecutive pair of every record is one frame, split
by camera setting (static or moving rig); the model's 3D pipeline, the oracle 3D flow through the same
post-processing and the 2.5D baselines (Farneback / true 2D flow, unstabilised and stabilised) are scored
against the same moving ground-truth boxes at 3D IoU 0.25 / 0.33 / 0.5.

Boxes are amodal by default (`--size-prior auto`, core.moving.amodal): for each 3D method a size prior
is estimated from that method's own components over the evaluated pairs — no labels — and for each 2.5D
flow source from its stabilised variant's clusters (both variants use it). `--size-prior none` keeps the
visible boxes; `--size-prior L W H` gives the prior in metres. Every method, 2.5D included, reads it.
"""

from __future__ import annotations

from core.device import resolve_device
from core.eval.protocols.moving import (CAMERAS, IOUS, MODEL, NEEDS, ORACLE_3D, PRIMARY_IOU, MovingEvalConfig,
                                        evaluate)
from core.eval.thresholds import threshold_key
from core.moving.amodal import SizePrior
from core.moving.ground import DEFAULT_MARGIN_VOXELS
from core.pipeline.moving import DEFAULT_DT, OCCUPANCY_SOURCES, MovingObjectsConfig
from services.cli.argtypes import non_negative_float, positive_float, positive_int, unit_fraction
from services.cli.eval import (add_eval_parser, add_rerun_option, check_rerun_option, iter_records,
                               load_bundle_for_eval, open_rerun_option, print_rerun_option)
from services.cli.eval_tasks.boxes_report import bev_boxes_figure, pr_figure
from services.reports import Report
from services.viz.rerun_paths import PAIR


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "moving", help="moving-object PR curves and AP (static/moving camera) "
                                                   "vs the 2.5D baselines")
    parser.add_argument("--dt", type=positive_float, default=DEFAULT_DT, help="seconds between steps (default %(default)s)")
    parser.add_argument("--min-speed", type=non_negative_float, default=MovingObjectsConfig.min_speed,
                        help="m/s above which a voxel moves (3D; default %(default)s)")
    parser.add_argument("--min-object-speed", type=non_negative_float, default=MovingObjectsConfig.min_object_speed,
                        help="m/s: a component whose mean velocity is slower is no moving object (default %(default)s)")
    parser.add_argument("--min-voxels", type=positive_int, default=3, help="smallest 3D component kept")
    parser.add_argument("--hysteresis", type=unit_fraction, default=MovingObjectsConfig.hysteresis,
                        help="voxels above this share of the speed threshold move when connected to one above it "
                             "(1: the threshold alone; default %(default)s)")
    parser.add_argument("--occupancy", choices=OCCUPANCY_SOURCES, default="observed",
                        help="voxels that can move: observed by frame 0's depth (default) or predicted by the "
                             "occupancy head (the paper's rule)")
    parser.add_argument("--no-ground", action="store_true",
                        help="do not drop the voxels at or below the ground plane fitted to frame 0's points")
    parser.add_argument("--flow-threshold-px", type=non_negative_float, default=1.0, help="2D flow (pixels) that moves (2.5D)")
    parser.add_argument("--min-pixels", type=positive_int, default=15, help="smallest 2D cluster kept (2.5D)")
    parser.add_argument("--min-points", type=positive_int, default=10,
                        help="depth points an object needs to count as ground truth")
    parser.add_argument("--no-baselines", action="store_true", help="skip the 2.5D baselines (faster)")
    parser.add_argument("--size-prior", nargs="+", default=["auto"], metavar="auto|none|L W H",
                        help="amodal boxes for every method, 2.5D baselines included: 'auto' (default) estimates "
                             "each 3D method's object size from its own components over these pairs (no labels) and "
                             "each 2.5D flow source's from its stabilised variant's, 'none' keeps the visible boxes, "
                             "three numbers give length, width and height in metres")
    add_rerun_option(parser)
    parser.set_defaults(func=run)


def parse_size_prior(words: list[str]) -> SizePrior | str | None:
    """--size-prior words -> "auto", None ("none") or a SizePrior (three positive numbers)."""
    from services.cli.main import CliError

    if words == ["auto"]:
        return "auto"
    if words == ["none"]:
        return None
    try:
        length, width, height = (float(w) for w in words)
        return SizePrior.from_size(length, width, height)
    except ValueError:
        raise CliError(f"--size-prior: expected 'auto', 'none' or three positive sizes L W H in metres, got "
                       f"{' '.join(words)!r}") from None


def build_report(bundle, records, config: MovingEvalConfig = MovingEvalConfig(), *, device, bundle_path=None,
                 data_path=None, max_records=None, recorder=None) -> Report:
    result = evaluate(bundle, records, config, device=device, recorder=recorder)
    objects, size_prior = config.objects, config.size_prior
    keys = [threshold_key(t) for t in IOUS]
    report = Report(kind="moving", title="Moving-object detection evaluation", bundle=bundle_path, data=data_path,
                    settings={"max_records": max_records, "pairs_static_camera": result["pairs"]["static"],
                              "pairs_moving_camera": result["pairs"]["moving"], "device": str(device),
                              "stabilised_with": result["stabilised_with"], "dt_s": objects.dt,
                              "min_speed_m_s": objects.min_speed, "hysteresis": objects.hysteresis,
                              "min_object_speed_m_s": objects.min_object_speed,
                              "min_voxels": objects.min_voxels,
                              "box_occupancy": objects.occupancy, "ground_margin_voxels": objects.ground_margin,
                              "flow_threshold_px": config.threshold_px, "min_pixels": config.min_pixels,
                              "gt_min_points": config.min_points,
                              "size_prior": "auto (per 3D method from its own components; per 2.5D flow source from its stabilised variant's)" if size_prior == "auto"
                              else (None if size_prior is None else size_prior.to_dict())})
    metrics = {cam: {m: a.summary() for m, a in per.items()} for cam, per in result["acc"].items()}
    report.metrics = {"moving": metrics, "moving_pairs": result["pairs"], "size_priors": result["size_priors"]}
    report.text("Each consecutive pair of a record is one frame. Ground truth: objects flagged moving, valid at "
                "both steps, centred in the grid and hit by at least `gt_min_points` depth points; boxes in "
                "ref_t. All-point interpolated AP over 3D IoU (exact, yaw-rotated). The paper reports IoU 0.5; "
                "0.25 and 0.33 are added because the tiny/small grids' voxels (1 m / 0.5 m) make voxel-fitted "
                "boxes coarse. `oracle 3d flow` runs the true flow and occupancy through the 3D "
                "post-processing (an upper bound of it); the 2.5D rows are the paper's baseline with "
                "Farneback or the true 2D flow, unstabilised and stabilised with the true camera motion.")
    for method, prior in result["size_priors"].items():
        report.text(f"Boxes of `{method}`: " + ("visible boxes (no size prior)." if prior is None else
                    f"amodal, size prior length {prior['length']:.2f} m, width {prior['width']:.2f} m, height "
                    f"{prior['height']:.2f} m (components above {prior['max_length']:.2f} × {prior['max_width']:.2f} "
                    f"× {prior['max_height']:.2f} m are split or dropped; box sides at most "
                    f"{prior['box_slack']:.2f} × the length and width)."))
    for cam in CAMERAS:
        report.heading(f"{cam.capitalize()} camera ({result['pairs'][cam]} pairs)")
        if result["pairs"][cam] == 0:
            report.text(f"No {cam}-camera pairs in this dataset: nothing to score.")
            continue
        rows = [[m, *[metrics[cam][m]["ap3d"][k] for k in keys], metrics[cam][m]["apbev"][threshold_key(PRIMARY_IOU)],
                 metrics[cam][m]["num_gt"], metrics[cam][m]["num_pred"]] for m in result["methods"]]
        report.table(["method", *[f"AP3D@{k}" for k in keys], f"APBEV@{threshold_key(PRIMARY_IOU)}",
                      "GT boxes", "detections"], rows)
        for iou in (PRIMARY_IOU, IOUS[0]):
            tag = threshold_key(iou).replace(".", "")
            report.figure(f"moving_pr_{cam}_iou{tag}",
                          pr_figure({m: result["acc"][cam][m].curve(iou) for m in result["methods"]},
                                    title=f"{cam} camera, 3D IoU {threshold_key(iou)}"),
                          f"Moving objects, {cam} camera: precision–recall at 3D IoU {threshold_key(iou)}")
    ex = result["example"]
    if ex is not None:
        v = bundle.preset.grid.voxel_size
        images = {MODEL: ex["bev"] * v, ORACLE_3D: ex["true_bev"] * v}
        shown = [m for m in (MODEL, ORACLE_3D, "2.5d farneback, stabilised") if m in ex["found"]]
        report.figure("moving_bev", bev_boxes_figure(bundle.preset.grid,
                                                     [(m, images.get(m), ex["gt"], ex["found"][m]) for m in shown],
                                                     image_label="|flow| (m per step), max over height",
                                                     suptitle=f"pair with the most moving objects ({ex['camera']} camera)"),
                      "Bird's-eye view: the model's and the true flow magnitude (max over height), true moving "
                      "boxes (green) and each method's top-10 boxes (red)")
    return report


def run(args) -> int:
    from services.viz.rerun_eval import close_eval_recorder

    size_prior = parse_size_prior(args.size_prior)   # a bad option is reported before any work
    check_rerun_option(args)
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    objects = MovingObjectsConfig(dt=args.dt, min_speed=args.min_speed, min_voxels=args.min_voxels,
                                  hysteresis=args.hysteresis, min_object_speed=args.min_object_speed,
                                  occupancy=args.occupancy,
                                  ground_margin=None if args.no_ground else DEFAULT_MARGIN_VOXELS)
    config = MovingEvalConfig(objects=objects, threshold_px=args.flow_threshold_px, min_pixels=args.min_pixels,
                              min_points=args.min_points, baselines=not args.no_baselines, size_prior=size_prior)
    recorder = open_rerun_option(args, bundle, timeline=PAIR, kind="moving")
    try:
        report = build_report(bundle, iter_records(args.data, args.max_records), config, device=device,
                              bundle_path=args.bundle, data_path=args.data, max_records=args.max_records,
                              recorder=recorder)
    finally:
        close_eval_recorder(recorder)
    out = report.write(args.out)
    key = threshold_key(PRIMARY_IOU)
    for cam in CAMERAS:
        if report.metrics["moving_pairs"][cam] == 0:
            continue
        per = report.metrics["moving"][cam]
        print(f"moving ({cam} camera, {report.metrics['moving_pairs'][cam]} pairs, {per[MODEL]['num_gt']} gt): "
              + ", ".join(f"{m} AP3D@{key} {_fmt(per[m]['ap3d'][key])}" for m in per))
    print(f"-> {out / 'report.md'}")
    print_rerun_option(args, recorder)
    return 0


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"
