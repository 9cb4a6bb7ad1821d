"""`n3dmap bench paper`: reproduce the paper's tables and figures on the synthetic world, end to end.

`run_paper_bench(config, out_dir)` runs, as resumable stages under OUT/work/ (services.bench.stages):

  data/train, data/test                 synthetic datasets (services.bench.data)
  seed<s>/pretrain_<arm>                view-contrastive and view-regression pretraining
  seed<s>/detector_<arm>_<mode>_L<N>    detector per arm (random/regression/contrastive), frozen or
                                        fine-tuned features, per label budget (trained on the first N
                                        records, RUN_DIR/labelled_data, as `train detector --labels N`)
  seed<s>/flow_<arm>                    3D flow over the frozen features of each pretrained arm
  seed<s>/flow_volume                   3D flow over the fused input volumes (n3dmap's default)
  seed<s>/egomotion                     the egomotion module
  seed<s>/eval/<kind>/<name>            one metrics.json per evaluation (detection mAP, retrieval,
                                        occupancy, flow EPE, egomotion vs ICP, moving objects)

then writes OUT/report.md, OUT/metrics.json and the PNG plots (services.bench.report). Training goes
through the training CLI's own job runner (services.bench.training); every evaluation is scored by the
`n3dmap eval` kinds' own `evaluate` functions (services/cli/eval_tasks, reduced to JSON by
services.bench.evaluations).
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
VOLUME_FLOW = "volume"   # the flow stage over fused input volumes (n3dmap's default), beside the per-arm ones


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
    from services.bench.data import generate_split

    train = stages.run("data/train", DATA_MARKER, lambda d: generate_split(
        d, preset=config.preset, episodes=config.train_episodes, seed=config.data_seed, split="train"))
    test = stages.run("data/test", DATA_MARKER, lambda d: generate_split(
        d, preset=config.preset, episodes=config.test_episodes, seed=config.data_seed + 1, split="val"))
    return {"train": train, "test": test}


# ----------------------------------------------------------------------------- one seed

def _seed_stages(stages: StageRunner, config: BenchConfig, seed: int, data: dict, test_records: list[dict],
                 device, preset) -> dict:
    from core.bundle import Bundle, load_bundle
    from services.bench import evaluations
    from services.bench.training import train_stage
    from services.cli.train_tasks.detector import labelled_subset

    s = f"seed{seed}"
    steps = config.steps

    def train(name: str, *, label_budget: int | None = None, data_dir: Path = data["train"], **kw) -> Path:
        def run(d: Path) -> None:
            # A label budget trains on the first N records, as `n3dmap train detector --labels N` does.
            source = data_dir if label_budget is None else labelled_subset(data_dir, d, label_budget)
            train_stage(config, run_dir=d, seed=seed, data_dir=source, **kw)
        return stages.run(f"{s}/{name}", TRAIN_MARKER, run) / "bundle"

    def evaluate(name: str, fn: Callable[[], dict]) -> dict:
        stage_dir = stages.run(f"{s}/eval/{name}", EVAL_MARKER, lambda d: write_json(d / EVAL_MARKER, _jsonable(fn())))
        return json.loads((stage_dir / EVAL_MARKER).read_text())

    pretrained = {arm: train(f"pretrain_{arm}", task="pretrain", steps=steps.pretrain,
                             task_options={"objective": arm}) for arm in PRETRAINED_ARMS}
    result: dict = {"detection": {}, "retrieval": {}, "occupancy": {}, "flow": {}}

    # Detection: every variant at every label budget.
    for arm, mode in config.detector_variants:
        for budget in config.budgets_sorted:
            name = detector_stage(arm, mode, budget)
            frozen = mode == "frozen"
            bundle_dir = train(name, task="detector", steps=steps.detector, label_budget=budget,
                               task_options={"labels": None, "freeze_features": frozen},
                               init_bundle=pretrained.get(arm), freeze=("mapper",) if frozen else (),
                               batch_size=min(config.batch_size or preset.train.batch_size,
                                              config.budget_records(budget)))
            result["detection"][f"{arm}/{mode}/{budget_name(budget)}"] = evaluate(
                f"detection/{arm}_{mode}_L{budget_name(budget)}",
                lambda b=bundle_dir: evaluations.detection(load_bundle(b, device), test_records, device=device))

    # Retrieval per arm (random: an untrained, seeded model).
    for arm in ("random", *PRETRAINED_ARMS):
        def retrieval(a=arm) -> dict:
            bundle = (evaluations.random_pretrain_bundle(preset, seed=seed, device=device) if a == "random"
                      else load_bundle(pretrained[a], device))
            return evaluations.retrieval(bundle, test_records, device=device, per_example=config.retrieval_per_example,
                                         cube=config.retrieval_cube, seed=seed)
        result["retrieval"][arm] = evaluate(f"retrieval/{arm}", retrieval)

    # Occupancy of each pretrained model's head, from one view (the paper's protocol).
    from services.cli.eval_tasks import occupancy as eval_occupancy
    for arm in PRETRAINED_ARMS:
        result["occupancy"][arm] = evaluate(f"occupancy/{arm}", lambda a=arm: eval_occupancy.evaluate(
            load_bundle(pretrained[a], device), test_records, device=device, input_view=0, threshold=0.5)["scores"])

    # 3D flow over the frozen features of each pretrained arm (the paper's protocol: the arms differ only
    # in the maps the flow module compares), and n3dmap's default flow, which compares the fused input
    # volumes (it does not depend on the pretraining; the contrastive bundle gives it the occupancy
    # head). All are scored against the zero-motion row.
    from services.cli.eval_tasks import flow as eval_flow
    flows = {arm: train(f"flow_{arm}", task="flow", steps=steps.flow, task_options={"inputs": "features"},
                        init_bundle=pretrained[arm], freeze=("mapper",)) for arm in PRETRAINED_ARMS}
    flows[VOLUME_FLOW] = train(f"flow_{VOLUME_FLOW}", task="flow", steps=steps.flow,
                               task_options={"inputs": "volume"}, init_bundle=pretrained["contrastive"],
                               freeze=("mapper",))
    for arm in (*PRETRAINED_ARMS, VOLUME_FLOW):
        result["flow"][arm] = evaluate(f"flow/{arm}", lambda a=arm: eval_flow.evaluate(
            load_bundle(flows[a], device), test_records, device=device, moving_threshold=1e-3)["scores"])

    # Egomotion vs ICP and identity, on the test pairs whose camera moves.
    from core.eval.egomotion_metrics import summarize_errors
    from core.eval.moving_protocol import camera_setting
    from services.cli.eval_tasks import egomotion as eval_egomotion
    ego_dir = train("egomotion", task="egomotion", steps=steps.egomotion)
    moving_cam = [r for r in test_records if r["rgb"].shape[0] > 1 and camera_setting(r, 0) == "moving"] or test_records

    def egomotion_metrics() -> dict:
        res = eval_egomotion.evaluate(load_bundle(ego_dir, device), moving_cam, device=device, perturb_deg=0.0,
                                      perturb_m=0.0, seed=seed, icp=True)
        return {"methods": {k: summarize_errors(v) for k, v in res["methods"].items()},
                "gt_motion": {k: float(v.mean()) for k, v in res["gt_motion"].items()}}
    result["egomotion"] = evaluate("egomotion/moving_camera", egomotion_metrics)

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
                                  threshold_px=config.flow2d_threshold_px, min_pixels=config.flow2d_min_pixels)
    result["moving"] = evaluate("moving/all", moving_metrics)
    return result


def _jsonable(value):
    """Tensors and numpy values -> plain JSON; NaN/inf -> None."""
    from services.reports.writer import json_safe

    return json_safe(value)
