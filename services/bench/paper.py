"""`n3dmap bench paper`: reproduce the paper's tables and figures on the synthetic world, end to end.

`run_paper_bench(config, out_dir)` runs, as resumable stages under OUT/work/ (services.bench.stages):

  data/train, data/test                 synthetic datasets (services.bench.data)
  data/labels_<N>                       the first N training records, one per label budget
  seed<s>/pretrain_<arm>                view-contrastive and view-regression pretraining
  seed<s>/detector_<arm>_<mode>_L<N>    detector per arm (random/regression/contrastive), frozen or
                                        fine-tuned features, per label budget
  seed<s>/flow_<arm>                    3D flow over the frozen features of each pretrained arm
  seed<s>/egomotion                     the egomotion module
  seed<s>/eval/...                      one metrics.json per evaluation (detection mAP, retrieval,
                                        occupancy, flow EPE, egomotion vs ICP, moving objects)

then writes OUT/report.md, OUT/metrics.json and the PNG plots (services.bench.report). Training goes
through the training CLI's own job runner (services.bench.training); flow, occupancy and egomotion are
scored by the `n3dmap eval` kinds' `evaluate` functions; detection, moving objects and retrieval by
services.bench.eval_* over the same core metrics.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import torch

from services.bench.plan import PRETRAINED_ARMS, BenchConfig
from services.bench.stages import StageRunner, write_json

TRAIN_MARKER = "bundle/bundle.json"
EVAL_MARKER = "metrics.json"
DATA_MARKER = "manifest.json"


def budget_name(budget: int | None) -> str:
    return "all" if budget is None else str(budget)


def detector_stage(arm: str, mode: str, budget: int | None) -> str:
    return f"detector_{arm}_{mode}_L{budget_name(budget)}"


def _device(choice: str) -> torch.device:
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(choice)


def run_paper_bench(config: BenchConfig, out_dir: str | Path, *, log: Callable[[str], None] = print) -> dict:
    """Run (or continue) the whole benchmark into `out_dir`; returns the report's metrics dict."""
    from core.presets import get_preset
    from services.bench.report import write_bench_report

    started = time.monotonic()
    out = Path(out_dir)
    stages = StageRunner(out / "work", log)
    _check_same_plan(out / "work" / "plan.json", config)
    device = _device(config.device)
    preset = get_preset(config.preset)
    log(f"[bench] paper benchmark, preset {config.preset}, seeds {list(config.seeds)}, device {device}, "
        f"{'quick profile' if config.quick else 'full profile'} -> {out}")

    data = _data_stages(stages, config)
    test_records = _load_records(data["test"])
    results: dict = {"seeds": {}}
    for seed in config.seeds:
        results["seeds"][str(seed)] = _seed_stages(stages, config, seed, data, test_records, device, preset)

    wall = time.monotonic() - started
    metrics = write_bench_report(out, config=config, results=results, stage_seconds=dict(stages.seconds),
                                 wall_time_s=wall, ran=list(stages.ran))
    log(f"[bench] report: {out / 'report.md'} ({wall:.1f} s this run; "
        f"{sum(v for v in stages.seconds.values() if v == v):.1f} s over all stages)")
    return metrics


def _check_same_plan(path: Path, config: BenchConfig) -> None:
    """A rerun into the same directory must use the same plan (else its stages would be mixed)."""
    from services.bench.plan import BenchConfigError

    current = {k: v for k, v in config.to_dict().items() if k not in ("seeds", "workers", "device")}
    if path.exists():
        earlier = {k: v for k, v in json.loads(path.read_text()).items() if k not in ("seeds", "workers", "device")}
        if earlier != current:
            changed = sorted(k for k in set(earlier) | set(current) if earlier.get(k) != current.get(k))
            raise BenchConfigError(f"{path.parent.parent} holds a benchmark with another plan "
                                   f"(differs in {changed}); use a new --out or the same options")
    write_json(path, config.to_dict())


def _load_records(data_dir: Path) -> list[dict]:
    from core.data.shards import ShardDataset

    dataset = ShardDataset(data_dir)
    return [dataset[i] for i in range(len(dataset))]


# ----------------------------------------------------------------------------- data

def _data_stages(stages: StageRunner, config: BenchConfig) -> dict:
    from services.bench.data import generate_split, write_label_subset

    train = stages.run("data/train", DATA_MARKER, lambda d: generate_split(
        d, preset=config.preset, episodes=config.train_episodes, seed=config.data_seed, split="train"))
    test = stages.run("data/test", DATA_MARKER, lambda d: generate_split(
        d, preset=config.preset, episodes=config.test_episodes, seed=config.data_seed + 1, split="val"))
    labels = {}
    for budget in config.label_budgets:
        if budget is None:
            labels[None] = train
        else:
            labels[budget] = stages.run(f"data/labels_{budget}", DATA_MARKER,
                                        lambda d, n=budget: write_label_subset(train, d, count=n))
    return {"train": train, "test": test, "labels": labels}


# ----------------------------------------------------------------------------- one seed

def _seed_stages(stages: StageRunner, config: BenchConfig, seed: int, data: dict, test_records: list[dict],
                 device, preset) -> dict:
    from core.bundle import Bundle, load_bundle
    from services.bench.training import train_stage

    s = f"seed{seed}"
    steps = config.steps

    def train(name: str, **kw) -> Path:
        run = stages.run(f"{s}/{name}", TRAIN_MARKER, lambda d: train_stage(config, run_dir=d, seed=seed, **kw))
        return run / "bundle"

    def evaluate(name: str, fn: Callable[[], dict]) -> dict:
        stage_dir = stages.run(f"{s}/eval/{name}", EVAL_MARKER, lambda d: write_json(d / EVAL_MARKER, _jsonable(fn())))
        return json.loads((stage_dir / EVAL_MARKER).read_text())

    pretrained = {arm: train(f"pretrain_{arm}", task="pretrain", data_dir=data["train"], steps=steps.pretrain,
                             task_options={"objective": arm}) for arm in PRETRAINED_ARMS}
    result: dict = {"detection": {}, "retrieval": {}, "occupancy": {}, "flow": {}}

    # Detection: every variant at every label budget.
    for arm, mode in config.detector_variants:
        for budget in config.budgets_sorted:
            name = detector_stage(arm, mode, budget)
            frozen = mode == "frozen"
            bundle_dir = train(name, task="detector", data_dir=data["labels"][budget], steps=steps.detector,
                               task_options={"labels": None, "freeze_features": frozen},
                               init_bundle=pretrained.get(arm), freeze=("mapper",) if frozen else (),
                               batch_size=min(config.batch_size or preset.train.batch_size,
                                              config.budget_records(budget)))
            from services.bench.eval_detection import evaluate_detection
            metrics = evaluate(name, lambda b=bundle_dir: evaluate_detection(
                load_bundle(b, device), test_records, device=device))
            result["detection"][f"{arm}/{mode}/{budget_name(budget)}"] = metrics

    # Retrieval per arm (random: untrained, seeded weights).
    from services.bench.eval_retrieval import evaluate_retrieval, pretrain_model
    for arm in ("random", *PRETRAINED_ARMS):
        result["retrieval"][arm] = evaluate(f"retrieval_{arm}", lambda a=arm: evaluate_retrieval(
            pretrain_model(preset, arm=a, bundle_dir=pretrained.get(a), seed=seed), test_records, device=device,
            per_example=config.retrieval_per_example, size=config.retrieval_patch, seed=seed))

    # Occupancy of each pretrained model's head, from one view (the paper's protocol).
    from services.cli.eval_tasks import occupancy as eval_occupancy
    for arm in PRETRAINED_ARMS:
        result["occupancy"][arm] = evaluate(f"occupancy_{arm}", lambda a=arm: eval_occupancy.evaluate(
            load_bundle(pretrained[a], device), test_records, device=device, input_view=0, threshold=0.5)["scores"])

    # 3D flow over the frozen features of each pretrained arm, scored against the zero-motion row.
    from services.cli.eval_tasks import flow as eval_flow
    flows = {arm: train(f"flow_{arm}", task="flow", data_dir=data["train"], steps=steps.flow,
                        init_bundle=pretrained[arm], freeze=("mapper",)) for arm in PRETRAINED_ARMS}
    for arm in PRETRAINED_ARMS:
        result["flow"][arm] = evaluate(f"flow_{arm}", lambda a=arm: eval_flow.evaluate(
            load_bundle(flows[a], device), test_records, device=device, moving_threshold=1e-3)["scores"])

    # Egomotion vs ICP and identity, on the test pairs whose camera moves.
    from core.eval.egomotion_metrics import summarize_errors
    from services.bench.eval_moving import camera_moves
    from services.cli.eval_tasks import egomotion as eval_egomotion
    ego_dir = train("egomotion", task="egomotion", data_dir=data["train"], steps=steps.egomotion)
    moving_cam = [r for r in test_records if r["rgb"].shape[0] > 1 and camera_moves(r)] or test_records

    def egomotion_metrics() -> dict:
        res = eval_egomotion.evaluate(load_bundle(ego_dir, device), moving_cam, device=device, perturb_deg=0.0,
                                      perturb_m=0.0, seed=seed, icp=True)
        return {"methods": {k: summarize_errors(v) for k, v in res["methods"].items()},
                "gt_motion": {k: float(v.mean()) for k, v in res["gt_motion"].items()}}
    result["egomotion"] = evaluate("egomotion", egomotion_metrics)

    # Moving objects: flow bundles (+ the egomotion module for the moving camera) vs the 2.5D baseline.
    from services.bench.eval_moving import evaluate_moving

    def moving_metrics() -> dict:
        ego = load_bundle(ego_dir, device).modules["egomotion"]
        bundles = {}
        for arm in PRETRAINED_ARMS:
            b = load_bundle(flows[arm], device)
            modes = ("poses",)
            if arm == "contrastive":
                b = Bundle(preset=b.preset, modules={**b.modules, "egomotion": ego}, meta=b.meta, path=b.path)
                modes = ("poses", "egomotion")
            bundles[arm] = (b, modes)
        return evaluate_moving(bundles, test_records, device=device, iou=config.moving_iou, grid=preset.grid,
                               flow2d_threshold=config.flow2d_threshold_px,
                               flow2d_min_pixels=config.flow2d_min_pixels)
    result["moving"] = evaluate("moving", moving_metrics)
    return result


def _jsonable(value):
    """Tensors and numpy values -> plain JSON; NaN/inf -> None."""
    from services.reports.writer import _clean

    return _clean(value)
