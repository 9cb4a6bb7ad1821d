"""The benchmark's evaluations: the evaluation protocols of `n3dmap eval` (core.eval.protocols), reduced to JSON.

Each function takes loaded bundles and the test records and returns a plain dict for a stage's
metrics.json (services.bench.paper); the scoring is entirely the protocols'. The bench only decides
which bundles to score and how to name the rows of the paper's tables.
"""

from __future__ import annotations

import torch

from core.bundle import Bundle

DETECTION_IOUS = (0.33, 0.5, 0.75)
MOVING_CURVE_POINTS = 50   # points kept per PR curve in metrics.json (for the plots)
# core.eval.protocols.moving's method names -> the report's rows (the 3D model rows are named per bundle).
MOVING_BASELINE_NAMES = {
    "oracle 3d flow": "oracle 3D flow (true flow, same post-processing)",
    "2.5d farneback": "2.5D Farneback",
    "2.5d farneback, stabilised": "2.5D Farneback stabilised",
    "2.5d oracle 2d flow": "2.5D oracle 2D flow",
    "2.5d oracle 2d flow, stabilised": "2.5D oracle 2D flow stabilised",
}


def detection(bundle: Bundle, records, *, device) -> dict:
    """mAP of a detector bundle: {"map": {iou: AP3D}, "map_bev": {iou: APBEV}, "gt_boxes", "detections", "frames"}."""
    from core.eval.protocols import detection as protocol

    result = protocol.evaluate(bundle, records, device=device, thresholds=DETECTION_IOUS)
    s = result["ap"].summary()
    return {"map": s["ap3d"], "map_bev": s["apbev"], "gt_boxes": s["num_gt"], "detections": s["num_pred"],
            "frames": result["frames"]}


def detection_over_draws(per_draw: list[dict]) -> dict:
    """One detector row from its label draws (each `detection`'s dict, same test records): mAP and BEV AP
    averaged per IoU over the draws, detections averaged, and "draws": each draw's mAP per IoU, in order.
    An IoU at which any draw has no AP (None: no ground-truth boxes) has no mean either (None), so that a
    claim reading it is undetermined rather than judged on the other draws."""
    def mean(key: str) -> dict:
        return {iou: None if any(d[key][iou] is None for d in per_draw)
                else sum(d[key][iou] for d in per_draw) / len(per_draw) for iou in per_draw[0][key]}

    return {"map": mean("map"), "map_bev": mean("map_bev"),
            "gt_boxes": per_draw[0]["gt_boxes"], "frames": per_draw[0]["frames"],
            "detections": sum(d["detections"] for d in per_draw) / len(per_draw),
            "draws": [dict(d["map"]) for d in per_draw]}


def random_pretrain_bundle(preset, *, seed: int, device, task_options: dict | None = None) -> Bundle:
    """The random-init arm: an untrained contrastive model's modules (seeded), as an in-memory bundle.
    task_options: the contrastive pretraining's (the plan's), so that the untrained model has the trained
    arms' architecture (e.g. the mapper's full-resolution branch)."""
    from core.tasks import build_task

    torch.manual_seed(seed)
    options = {**(task_options or {}), "objective": "contrastive"}
    task = build_task("pretrain", preset, **options).to(device).eval()
    return Bundle(preset=preset, modules=dict(task.exported_modules()), meta={"provenance": {"random_init": seed}})


def untrained_egomotion_bundle(preset, *, seed: int, device) -> Bundle:
    """The egomotion stage's module untrained (seeded), with the same last stage, as an in-memory bundle: the
    control that says how much of the module's accuracy its training brings."""
    from core.tasks import build_task

    torch.manual_seed(seed)
    task = build_task("egomotion", preset).to(device).eval()
    return Bundle(preset=preset, modules=dict(task.exported_modules()), meta={"provenance": {"random_init": seed}})


def egomotion_with_control(trained: Bundle, untrained: Bundle, records, config, *, device) -> dict:
    """core.eval.protocols.egomotion's summary of `trained` (its rows, ICP and identity), plus the untrained
    module's own rows renamed "untrained module" and "untrained module, learned stages only"."""
    from dataclasses import replace

    from core.eval.protocols import egomotion as protocol

    summary = protocol.summarize(protocol.evaluate(trained, records, config, device=device))
    control = protocol.summarize(protocol.evaluate(untrained, records, replace(config, icp=False), device=device))
    for name, row in control["methods"].items():
        if name.startswith("model"):
            summary["methods"]["untrained module" + name[len("model"):]] = row
    return summary


def retrieval(bundle: Bundle, records, *, device, per_example: int, cube: int, seed: int) -> dict:
    """{"2d": {"p@1", "p@5", "p@10", "queries"}, "3d": {...}, "mode_2d", "skipped"}."""
    from core.eval.protocols.retrieval import RetrievalEvalConfig, evaluate

    result = evaluate(bundle, records, RetrievalEvalConfig(per_example=per_example, cube_3d=cube, seed=seed),
                      device=device)
    nan = {"p@1": float("nan"), "p@5": float("nan"), "p@10": float("nan"), "queries": 0}
    return {"2d": result["scores"].get("2d", nan), "3d": result["scores"].get("3d", nan),
            "mode_2d": result["mode_2d"], "skipped": result["skipped"]}


def moving(model_bundles: dict[str, Bundle], records, *, device, iou: float, threshold_px: float,
           min_pixels: int, dt: float) -> dict:
    """Moving-object AP per camera setting for each named flow bundle (its "3d (model)" row) plus, from
    the first bundle's run, the oracle-3D-flow and 2.5D baseline rows. A bundle holding an `egomotion`
    module is stabilised with it, otherwise with the record poses (the protocol's rule). dt: seconds between
    the records' steps (the world's), which turns the boxes' speed threshold (m/s) into voxels per pair.

    Returns {"iou", "pairs": {setting: n}, setting: {method: {"ap", "ap_by_iou", "gt_boxes",
    "detections", "curve": {"precision", "recall"}}}}.
    """
    from core.eval.protocols import moving as protocol
    from core.eval.thresholds import threshold_key
    from core.pipeline.moving import MovingObjectsConfig

    out: dict = {"iou": iou}
    for i, (name, bundle) in enumerate(model_bundles.items()):
        config = protocol.MovingEvalConfig(objects=MovingObjectsConfig(dt=dt), threshold_px=threshold_px,
                                           min_pixels=min_pixels, min_points=10, baselines=i == 0)
        result = protocol.evaluate(bundle, records, config, device=device)
        out["pairs"] = result["pairs"]
        for setting, per_method in result["acc"].items():
            rows = out.setdefault(setting, {})
            for method, acc in per_method.items():
                label = name if method == protocol.MODEL else MOVING_BASELINE_NAMES.get(method, method)
                if method != protocol.MODEL and i > 0:
                    continue  # the baselines do not depend on the bundle: kept from the first run
                s = acc.summary()
                precision, recall = acc.curve(iou) if iou in acc.thresholds else acc.curve(protocol.PRIMARY_IOU)
                keep = _subsample(len(recall), MOVING_CURVE_POINTS)
                rows[label] = {"ap": s["ap3d"].get(threshold_key(iou)), "ap_by_iou": s["ap3d"],
                               "gt_boxes": s["num_gt"], "detections": s["num_pred"],
                               "curve": {"precision": [float(precision[j]) for j in keep],
                                         "recall": [float(recall[j]) for j in keep]}}
    return out


def _subsample(n: int, points: int) -> list[int]:
    if n <= points:
        return list(range(n))
    return sorted({round(i * (n - 1) / (points - 1)) for i in range(points)})
