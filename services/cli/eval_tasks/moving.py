"""`n3dmap eval moving`: unsupervised moving-object detection, PR curves and AP (paper §5).

Every consecutive pair (t, t+1) of every record is one frame, split by camera setting (static or
moving rig, from the records' true ego motion). Methods, all scored against the same ground truth
(core.eval.moving_protocol.gt_moving_boxes: moving objects in the grid and seen by ≥ min-points depth
points, boxes in ref_t):
- `3d (model)`: core.pipeline.moving_objects — stabilise (the bundle's egomotion estimate if it has
  one, else the record poses), 3D flow, free voxels zeroed, components / saliency / box fit / NMS;
- `oracle 3d flow`: the true stabilised 3D flow (core.data.ground_truth.gt_flow) with the true
  occupancy through the same post-processing — an upper bound of the 3D pipeline's post-processing;
- `2.5d farneback` / `2.5d oracle 2d flow`, each unstabilised and stabilised (the paper's baseline:
  2D flow, thresholded, clustered, lifted with depth; per view, merged across the rig by BEV NMS).
AP is all-point interpolated at 3D IoU 0.5 (the paper's) and 0.25 / 0.33: at the tiny and small
presets voxels are 1 m and 0.5 m, so a box fitted to voxels is coarse and IoU 0.5 is a hard bar.

Boxes are amodal by default (`--size-prior auto`, core.moving.amodal): for each 3D method a size prior
is estimated from that method's own components over the evaluated pairs — no labels — and every
component is split or dropped when oversized and grown to a whole object away from the camera.
`--size-prior none` keeps the visible boxes; `--size-prior L W H` gives the prior in metres.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from core.data.ground_truth import gt_flow, gt_occupancy, points_in_ref
from core.eval.moving_protocol import camera_setting, gt_moving_boxes, moving_objects_2p5d_rig
from core.geometry import se3
from core.moving.amodal import SizePrior, estimate_size_prior
from core.moving.ground import DEFAULT_MARGIN_VOXELS, fit_ground_plane
from core.pipeline.egomotion import rig_cam_T_ref
from core.pipeline.moving import DEFAULT_DT, OCCUPANCY_SOURCES, MovingObjectsConfig, boxes_from_flow, moving_objects
from services.cli.argtypes import non_negative_float, positive_float, positive_int
from services.cli.eval import (add_eval_parser, add_rerun_option, check_rerun_option, iter_records,
                               load_bundle_for_eval, open_rerun_option, print_rerun_option, resolve_device)
from services.cli.eval_detection import threshold_key
from services.cli.eval_tasks.boxes_report import MethodAP, bev_boxes_figure, pr_figure
from services.cli.eval_tasks.common import pair_inputs, record_batch
from services.reports import Report
from services.viz.rerun_paths import PAIR

NEEDS = ("mapper", "flow")
IOUS = (0.25, 0.33, 0.5)
PRIMARY_IOU = 0.5
CAMERAS = ("static", "moving")
MODEL, ORACLE_3D = "3d (model)", "oracle 3d flow"
BASELINES = {  # method -> (2D flow source, stabilised)
    "2.5d farneback": ("farneback", False),
    "2.5d farneback, stabilised": ("farneback", True),
    "2.5d oracle 2d flow": ("oracle", False),
    "2.5d oracle 2d flow, stabilised": ("oracle", True),
}
METHODS = (MODEL, ORACLE_3D, *BASELINES)


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "moving", help="moving-object PR curves and AP (static/moving camera) "
                                                   "vs the 2.5D baselines")
    parser.add_argument("--dt", type=positive_float, default=DEFAULT_DT, help="seconds between steps (default %(default)s)")
    parser.add_argument("--min-speed", type=non_negative_float, default=1.0, help="m/s above which a voxel moves (3D)")
    parser.add_argument("--min-voxels", type=positive_int, default=3, help="smallest 3D component kept")
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
                        help="amodal boxes: 'auto' (default) estimates each method's object size from its own "
                             "components over these pairs (no labels), 'none' keeps the visible boxes, three "
                             "numbers give length, width and height in metres")
    add_rerun_option(parser)
    parser.set_defaults(func=run)


def _np(boxes: torch.Tensor, scores: torch.Tensor, valid: torch.Tensor):
    return boxes[valid].double().cpu().numpy(), scores[valid].double().cpu().numpy()


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


def _oracle(record, t, grid, config: MovingObjectsConfig) -> dict:
    """The true stabilised flow and occupancy through the post-processing of `config` (1-item batch)."""
    true_flow = gt_flow(record, t, grid)[None]                                  # 1×3×Z×Y×X
    xyz, valid = points_in_ref(record, t)                                       # the same ground plane rule
    ground = [fit_ground_plane(xyz[valid].double().numpy()) if config.ground_margin is not None else None]
    cam_T_ref = rig_cam_T_ref(torch.as_tensor(record["world_T_cam"][t], dtype=torch.float64)[None],
                              torch.as_tensor(record["world_T_ref"][t], dtype=torch.float64)[None])  # 1×V×4×4
    viewpoints = se3.invert(cam_T_ref)[..., :3, 3].float()                      # 1×V×3 camera centres in ref
    observed = gt_occupancy(record, t, grid)[None]                              # 1×1×Z×Y×X
    out = boxes_from_flow(true_flow, observed, grid, config, ground=ground, viewpoints=viewpoints)
    return {**out, "flow": true_flow, "observed": observed}


def method_configs(bundle, records, *, device, config: MovingObjectsConfig, size_prior) -> dict:
    """{MODEL: config, ORACLE_3D: config} with each method's size prior: `size_prior` a SizePrior or None
    for both, or "auto": estimated from that method's own visible components over `records` (no labels)."""
    if size_prior != "auto":
        return {MODEL: replace(config, size_prior=size_prior), ORACLE_3D: replace(config, size_prior=size_prior)}
    visible = replace(config, size_prior=None)
    extents = {MODEL: [], ORACLE_3D: []}
    for record in records:
        batch = record_batch(record, device)
        for t in range(batch["rgb"].shape[1] - 1):
            for name, out in ((MODEL, moving_objects(bundle, **pair_inputs(batch, t, t + 1), config=visible)),
                              (ORACLE_3D, _oracle(record, t, bundle.preset.grid, visible))):
                boxes = out["boxes"][0][out["valid"][0]].double().cpu().numpy()
                extents[name] += list(boxes[:, 3:6])
    configs = {}
    for name, found in extents.items():
        # No component at all: nothing to estimate from, so the boxes stay visible boxes.
        configs[name] = replace(config, size_prior=estimate_size_prior(np.array(found)) if found else None)
    return configs


def evaluate(bundle, records, *, device, config: MovingObjectsConfig, threshold_px: float, min_pixels: int,
             min_points: int, baselines: bool = True, size_prior="auto", recorder=None) -> dict:
    """AP accumulators per camera setting × method, pair counts, the size prior each 3D method used and
    the richest example for a plot. size_prior: "auto", None or a SizePrior (method_configs).
    `recorder` (services.viz.rerun_eval.EvalRecorder) gets every pair: observed occupancy, the true and
    the model's flow, the ground-truth moving boxes and the model's boxes with scores."""
    grid = bundle.preset.grid
    records = list(records)
    configs = method_configs(bundle, records, device=device, config=config, size_prior=size_prior)
    methods = METHODS if baselines else (MODEL, ORACLE_3D)
    acc = {cam: {m: MethodAP(IOUS) for m in methods} for cam in CAMERAS}
    pairs = {cam: 0 for cam in CAMERAS}
    stabilised_with = "egomotion (bundle)" if "egomotion" in bundle.modules else "poses (records)"
    example = None
    for record_index, record in enumerate(records):
        batch = record_batch(record, device)
        for t in range(batch["rgb"].shape[1] - 1):
            cam = camera_setting(record, t)
            gt = gt_moving_boxes(record, t, grid, min_points=min_points)
            found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
            out = moving_objects(bundle, **pair_inputs(batch, t, t + 1), config=configs[MODEL])
            found[MODEL] = _np(out["boxes"][0], out["scores"][0], out["valid"][0])
            oracle = _oracle(record, t, grid, configs[ORACLE_3D])
            true_flow, observed = oracle["flow"], oracle["observed"]
            found[ORACLE_3D] = _np(oracle["boxes"][0], oracle["scores"][0], oracle["valid"][0])
            if baselines:
                for name, (source, stabilise) in BASELINES.items():
                    found[name] = moving_objects_2p5d_rig(record, t, flow_source=source, stabilise=stabilise,
                                                          threshold_px=threshold_px, min_pixels=min_pixels,
                                                          dt=config.dt, nms_iou=config.nms_iou)
            for name, (boxes, scores) in found.items():
                acc[cam][name].add_frame(boxes, scores, gt)
            pairs[cam] += 1
            if recorder is not None:
                recorder.log_entry(record=record, record_index=record_index, t0=t, t1=t + 1,
                                   occupancy=observed[0, 0].numpy() > 0.5, flow_true=true_flow[0].numpy(),
                                   flow_pred=out["flow"][0].float().cpu().numpy(), boxes_true=gt,
                                   boxes_pred=found[MODEL][0], scores_pred=found[MODEL][1], note=f"{cam} camera")
            if example is None or len(gt) > len(example["gt"]):
                bev = out["flow"][0].norm(dim=0).amax(dim=1).cpu().numpy()      # Z×X voxels
                example = {"gt": gt, "bev": bev, "camera": cam,
                           "true_bev": true_flow[0].norm(dim=0).amax(dim=1).numpy(),
                           "found": {k: v[0][:10] for k, v in found.items()}}
    if sum(pairs.values()) == 0:
        from services.cli.main import CliError
        raise CliError("moving-object evaluation needs records with at least 2 time steps")
    priors = {m: None if c.size_prior is None else c.size_prior.to_dict() for m, c in configs.items()}
    return {"acc": acc, "pairs": pairs, "example": example, "stabilised_with": stabilised_with, "methods": methods,
            "size_priors": priors}


def build_report(bundle, records, *, device, config: MovingObjectsConfig, threshold_px: float = 1.0,
                 min_pixels: int = 15, min_points: int = 10, baselines: bool = True, bundle_path=None,
                 data_path=None, max_records=None, size_prior="auto", recorder=None) -> Report:
    result = evaluate(bundle, records, device=device, config=config, threshold_px=threshold_px,
                      min_pixels=min_pixels, min_points=min_points, baselines=baselines, size_prior=size_prior,
                      recorder=recorder)
    keys = [threshold_key(t) for t in IOUS]
    report = Report(kind="moving", title="Moving-object detection evaluation", bundle=bundle_path, data=data_path,
                    settings={"max_records": max_records, "pairs_static_camera": result["pairs"]["static"],
                              "pairs_moving_camera": result["pairs"]["moving"], "device": str(device),
                              "stabilised_with": result["stabilised_with"], "dt_s": config.dt,
                              "min_speed_m_s": config.min_speed, "min_voxels": config.min_voxels,
                              "box_occupancy": config.occupancy, "ground_margin_voxels": config.ground_margin,
                              "flow_threshold_px": threshold_px, "min_pixels": min_pixels,
                              "gt_min_points": min_points,
                              "size_prior": "auto (per method, from its own components)" if size_prior == "auto"
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
                    f"× {prior['max_height']:.2f} m are split or dropped)."))
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
    config = MovingObjectsConfig(dt=args.dt, min_speed=args.min_speed, min_voxels=args.min_voxels,
                                 occupancy=args.occupancy, ground_margin=None if args.no_ground else DEFAULT_MARGIN_VOXELS)
    recorder = open_rerun_option(args, bundle, timeline=PAIR, kind="moving")
    try:
        report = build_report(bundle, iter_records(args.data, args.max_records), device=device, config=config,
                              threshold_px=args.flow_threshold_px, min_pixels=args.min_pixels,
                              min_points=args.min_points, baselines=not args.no_baselines, bundle_path=args.bundle,
                              data_path=args.data, max_records=args.max_records,
                              size_prior=size_prior, recorder=recorder)
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
