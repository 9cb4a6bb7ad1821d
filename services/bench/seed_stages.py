"""One seed's stage graph of `n3dmap bench paper`: what each seed trains and evaluates, in order, as resumable
stages (services.bench.stages) whose names and specs (digests) are the benchmark's identity — renaming a stage or
changing what its spec holds makes a rerun redo it. services.bench.paper runs it for every seed (in this process
or in seed workers); services.bench.replan walks it without running anything to learn which stages a change
of plan touches.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from services.bench.plan import OCCUPANCY_MODULE, OCCUPANCY_MODULE_AT_HALF, PRETRAINED_ARMS, BenchConfig
from services.bench.stages import StageRunner, write_json
from services.bench.stopping import MARKER as TRAIN_MARKER

EVAL_MARKER = "metrics.json"
VOLUME_FLOW = "volume"   # the flow stage over fused input volumes (n3dmap's default), beside the per-arm ones


def budget_name(budget: int | None) -> str:
    return "all" if budget is None else str(budget)


def detector_stage(arm: str, mode: str, budget: int | None, draw: int = 0) -> str:
    """Draw 0 keeps the name it had before label draws existed, so a plan of one draw keeps its stages."""
    return f"detector_{arm}_{mode}_L{budget_name(budget)}" + (f"_draw{draw}" if draw else "")



# Plan fields a training stage's output depends on besides its own task, options, rule and inputs, and the
# ones each kind of evaluation reads besides the data and its bundles (the stage digests of
# services.bench.stages; the data's fields reach every stage through the data stages' digests, `seeds` are
# in the names, and `workers` / `device` are not part of a plan's identity, as in _check_same_plan).
TRAINING_PLAN_FIELDS = ("preset", "train_episodes", "val_episodes", "data_seed", "batch_size", "precision", "quick")
EVAL_PLAN_FIELDS = {"retrieval": ("retrieval_per_example", "retrieval_cube"),
                    "moving": ("moving_iou", "flow2d_threshold_px", "flow2d_min_pixels")}


def _plan_fields(config: BenchConfig, names: tuple[str, ...]) -> dict:
    plan = config.to_dict()
    return {name: plan[name] for name in names}


def seed_stages(stages: StageRunner, config: BenchConfig, seed: int, data: dict, test_records: list[dict],
                val_records: list[dict], device) -> dict:
    """Run (or, with a dry StageRunner, record) every stage of seed `seed`; returns its results by kind
    ("detection", "retrieval", "occupancy", "flow", "egomotion", "moving"), each evaluation's metrics.json.
    data: the data stages' directories {"train" | "val" | "test": Path}; test_records / val_records: those
    datasets' records (empty for a dry run)."""
    from core.bundle import Bundle, load_bundle
    from core.presets import get_preset
    from services.bench import evaluations
    from services.bench.stopping import SELECTED
    from services.bench.training import train_stage
    from services.training.label_subset import labelled_subset

    preset = get_preset(config.preset)
    s = f"seed{seed}"
    rules = config.rules

    def train(name: str, *, label_budget: int | None = None, label_draw: int = 0, data_dir: Path = data["train"],
              **kw) -> Path:
        def run(d: Path) -> None:
            # A label budget trains on the first N records, as `n3dmap train detector --labels N` does (draw
            # d > 0: records [d·N, (d+1)·N)).
            source = data_dir if label_budget is None else labelled_subset(
                data_dir, d, label_budget, first=label_draw * label_budget, log=print)
            train_stage(config, run_dir=d, seed=seed, data_dir=source, heldout_records=val_records, **kw)
        unknown = set(kw) - {"task", "rule", "task_options", "init_bundle", "freeze", "batch_size"}
        if unknown:  # each must be in the stage's spec below, or a changed value would not rerun the stage
            raise TypeError(f"train(): no stage spec for {sorted(unknown)}")
        init = kw.get("init_bundle")
        spec = {"task": kw["task"], "rule": kw["rule"].to_dict(), "task_options": kw.get("task_options") or {},
                "freeze": list(kw.get("freeze", ())), "batch_size": kw.get("batch_size"), "label_budget": label_budget,
                "plan": _plan_fields(config, TRAINING_PLAN_FIELDS)}
        if label_draw:   # only then: draw 0's spec (digest) stays what it was before label draws existed
            spec["label_draw"] = label_draw
        after = [stages.name_of(data_dir), stages.name_of(data["val"]), *([stages.name_of(init)] if init else [])]
        return stages.run(f"{s}/{name}", TRAIN_MARKER, run, spec=spec, after=after) / SELECTED

    def evaluate(name: str, fn: Callable[[], dict], reads: tuple[Path, ...] = ()) -> dict:
        """Evaluation stage `name`: fn's metrics; reads: the bundles (training stages' outputs) fn loads."""
        kind = name.split("/")[0]
        after = [stages.name_of(data["test"]), stages.name_of(data["val"]), *(stages.name_of(r) for r in reads)]
        stage_dir = stages.run(f"{s}/eval/{name}", EVAL_MARKER, lambda d: write_json(d / EVAL_MARKER, _jsonable(fn())),
                               spec={"plan": _plan_fields(config, ("preset", *EVAL_PLAN_FIELDS.get(kind, ())))},
                               after=after)
        return {} if stages.dry else json.loads((stage_dir / EVAL_MARKER).read_text())

    pretrained = {arm: train(f"pretrain_{arm}", task="pretrain", rule=rules.pretrain,
                             task_options=config.stage_options("pretrain", {"objective": arm}))
                  for arm in PRETRAINED_ARMS}
    result: dict = {"detection": {}, "retrieval": {}, "occupancy": {}, "flow": {}}

    # 3D flow first, right after the pretrainings (the order changes no number: every stage is seeded on its
    # own): the flow claims are the ones a change of the pretrainings is made for, so a regeneration answers
    # them ~3 h sooner than after the detectors and occupancy.
    # 3D flow over the frozen features of each pretrained arm (the paper's protocol: the arms differ only
    # in the maps the flow module compares), and n3dmap's default flow, which compares the fused input
    # volumes (it does not depend on the pretraining; the contrastive bundle gives it the occupancy
    # head). All are scored against the zero-motion row.
    from core.eval.protocols import flow as flow_protocol
    flows = {arm: train(f"flow_{arm}", task="flow", rule=rules.flow,
                        task_options=config.stage_options("flow_features", {"inputs": "features"}),
                        init_bundle=pretrained[arm], freeze=("mapper",)) for arm in PRETRAINED_ARMS}
    flows[VOLUME_FLOW] = train(f"flow_{VOLUME_FLOW}", task="flow", rule=rules.flow,
                               task_options=config.stage_options("flow_volume", {"inputs": "volume"}),
                               init_bundle=pretrained["contrastive"],
                               freeze=("mapper",))
    for arm in (*PRETRAINED_ARMS, VOLUME_FLOW):
        result["flow"][arm] = evaluate(f"flow/{arm}", lambda a=arm: flow_protocol.evaluate(
            load_bundle(flows[a], device), test_records, device=device, moving_threshold=1e-3)["scores"],
            reads=(flows[arm],))

    # Detection: every variant at every label budget; the smallest budget once per label draw, its rows the
    # mean over the draws.
    for arm, mode in config.detector_variants:
        for budget in config.budgets_sorted:
            frozen = mode == "frozen"
            per_draw = []
            for draw in range(config.draws_of(budget)):
                name = detector_stage(arm, mode, budget, draw)
                bundle_dir = train(name, task="detector", rule=rules.detector, label_budget=budget, label_draw=draw,
                                   task_options=config.stage_options(
                                       "detector", {"labels": None, "freeze_features": frozen}),
                                   init_bundle=pretrained.get(arm), freeze=("mapper",) if frozen else (),
                                   batch_size=config.detector_batch_size(budget, preset.train.batch_size))
                per_draw.append(evaluate(
                    f"detection/{name[len('detector_'):]}",
                    lambda b=bundle_dir: evaluations.detection(load_bundle(b, device), test_records, device=device),
                    reads=(bundle_dir,)))
            result["detection"][f"{arm}/{mode}/{budget_name(budget)}"] = (
                per_draw[0] if len(per_draw) == 1 or stages.dry else evaluations.detection_over_draws(per_draw))

    # Retrieval per arm (random: an untrained, seeded model).
    for arm in ("random", *PRETRAINED_ARMS):
        def retrieval(a=arm) -> dict:
            if a == "random":   # the contrastive arm's model, untrained
                bundle = evaluations.random_pretrain_bundle(
                    preset, seed=seed, device=device,
                    task_options=config.stage_options("pretrain", {"objective": "contrastive"}))
            else:
                bundle = load_bundle(pretrained[a], device)
            return evaluations.retrieval(bundle, test_records, device=device, per_example=config.retrieval_per_example,
                                         cube=config.retrieval_cube, seed=seed)
        result["retrieval"][arm] = evaluate(f"retrieval/{arm}", retrieval,
                                            reads=() if arm == "random" else (pretrained[arm],))

    # Occupancy from one view (the paper's protocol). The claim reads the occupancy module trained the way
    # it is tested (a map of one view, labels from it and one other view; `n3dmap train occupancy`), mapper
    # fine-tuned from the contrastive pretraining, at the balanced threshold chosen on the validation records
    # with each of their views as the input in turn (occupancy_protocol.choose_balanced_threshold); the same
    # module at 0.5 beside it. Each pretraining's own head is read too: it is trained on maps fused from all
    # views but one, so a single view's map is not what it learned on.
    from core.eval.protocols import occupancy as occupancy_protocol

    def occupancy_scores(bundle, threshold: float = 0.5) -> dict:
        return occupancy_protocol.evaluate(bundle, test_records,
                                           occupancy_protocol.OccupancyEvalConfig(input_view=0, threshold=threshold),
                                           device=device)["scores"]

    def balanced_scores(bundle_dir: Path) -> dict:
        bundle = load_bundle(bundle_dir, device)
        threshold, on_val = occupancy_protocol.choose_balanced_threshold(bundle, val_records, device=device)
        return {**occupancy_scores(bundle, threshold), "threshold": threshold,
                "val_acc_occupied": on_val["acc_occupied"], "val_acc_free": on_val["acc_free"]}
    occupancy_dir = train("occupancy_contrastive", task="occupancy", rule=rules.occupancy,
                          task_options=config.stage_options("occupancy", {}), init_bundle=pretrained["contrastive"])
    result["occupancy"][OCCUPANCY_MODULE] = evaluate("occupancy/module_contrastive_balanced",
                                                     lambda: balanced_scores(occupancy_dir), reads=(occupancy_dir,))
    result["occupancy"][OCCUPANCY_MODULE_AT_HALF] = evaluate(
        "occupancy/module_contrastive", lambda: occupancy_scores(load_bundle(occupancy_dir, device)),
        reads=(occupancy_dir,))
    for arm in PRETRAINED_ARMS:
        result["occupancy"][f"{arm}, pretraining head"] = evaluate(
            f"occupancy/{arm}", lambda a=arm: occupancy_scores(load_bundle(pretrained[a], device)),
            reads=(pretrained[arm],))

    # Egomotion vs ICP and identity, on the test pairs whose camera moves.
    from core.eval.moving_protocol import camera_setting
    from core.eval.protocols import egomotion as egomotion_protocol
    ego_dir = train("egomotion", task="egomotion", rule=rules.egomotion)
    # No fallback to other pairs: the claim is about a moving camera (none among the test records: no
    # numbers, so the claim is undetermined).
    moving_cam = [r for r in test_records if r["rgb"].shape[0] > 1 and camera_setting(r, 0) == "moving"]

    def egomotion_metrics() -> dict:
        if not moving_cam:
            return {"methods": {}, "skipped": "no moving-camera pairs among the test records"}
        ego_config = egomotion_protocol.EgomotionEvalConfig(perturb_deg=0.0, perturb_m=0.0, seed=seed, icp=True)
        # beside it the same module untrained: its weightless last stage alone may reach ICP (session 25)
        return evaluations.egomotion_with_control(
            load_bundle(ego_dir, device), evaluations.untrained_egomotion_bundle(preset, seed=seed, device=device),
            moving_cam, ego_config, device=device)
    result["egomotion"] = evaluate("egomotion/moving_camera", egomotion_metrics, reads=(ego_dir,))

    # Moving objects: each flow bundle stabilised with the poses, the contrastive-feature and the
    # input-volume ones also with the trained egomotion module; the 2.5D baselines come with the first.
    def moving_metrics() -> dict:
        ego = load_bundle(ego_dir, device).modules["egomotion"]

        def with_egomotion(bundle: Bundle) -> Bundle:
            return Bundle(preset=bundle.preset, modules={**bundle.modules, "egomotion": ego}, meta=bundle.meta,
                          path=bundle.path)
        contrastive, volume = load_bundle(flows["contrastive"], device), load_bundle(flows[VOLUME_FLOW], device)
        bundles = {"contrastive, GT egomotion": contrastive,
                   "contrastive, egomotion module": with_egomotion(contrastive),
                   "regression, GT egomotion": load_bundle(flows["regression"], device),
                   "input volumes, GT egomotion": volume,
                   "input volumes, egomotion module": with_egomotion(volume)}
        return evaluations.moving(bundles, test_records, device=device, iou=config.moving_iou,
                                  threshold_px=config.flow2d_threshold_px, min_pixels=config.flow2d_min_pixels,
                                  dt=config.world_config().dt)   # the world's step (a new world reruns via the data)
    result["moving"] = evaluate("moving/all", moving_metrics, reads=(*flows.values(), ego_dir))
    return result


def _jsonable(value):
    """Tensors and numpy values -> plain JSON; NaN/inf -> None."""
    from services.reports.writer import json_safe

    return json_safe(value)
