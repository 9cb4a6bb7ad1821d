"""How much does the choice of labelled records move the few-label detection verdict?

    python tests/benchmarks/bench_label_draws.py --work REPORT_DIR/work --heldout DIR --out OUT
        [--seeds 0 1 2] [--arms contrastive regression] [--draws 0 1 2 3 4 5 6 7] [--budget 2]
        [--pretrain-steps N --pretrain-options JSON | --continue-pretraining N] [--frozen]
        [--detector-steps N [N ...]]
        [--device cpu|cuda] [--threads 1] [--heldout-seed 7 [--heldout-episodes 32]]

For each seed of a `bench paper` work directory and each pretraining arm, trains the fine-tuned detector
(with --frozen: the pretrained arms' detectors on frozen features, the paper's protocol and the few-label
claim's rows; random init is always trained end to end) the way the benchmark does (its plan's stopping
rule and task options, `services.bench.training.train_stage`) on label draw d — training records d·N … (d+1)·N − 1, `labelled_subset(first=d·N)`; draw 0
is the benchmark's own set — with detector seed s + 100·d, and scores mAP on DIR's records (use records
that are not the benchmark's test set). With --pretrain-steps N each arm is first pretrained here for N
fixed steps with the plan's pretraining options updated by --pretrain-options (e.g. '{"coeff_match": 0}'
for the paper's objectives without the matching term) instead of reading the benchmark's pretraining.
With --continue-pretraining N each arm's benchmark pretraining that stopped before step N is continued to N
(a copy of its newest complete checkpoint in OUT/seed<s>_pretrain_<arm>_to<N>, the same options and per-step
seeds, so the same run as if its rule had let it go on; the learning rate is constant) and its step-N weights are
the arm's; an arm that already ran N steps keeps its benchmark selection (was the plateau rule's stop too early?).
With --detector-steps N the detectors train N fixed steps instead of the plan's rule (is that rule long
enough to converge?); with several lengths (ascending) each detector is scored at every one of them, one
run continued from the last (the learning rate is constant and every step seeded from (seed, step), so
that is the same as training each length from the start wherever an epoch is one step, as at 2 labels
and batch 2; with more steps per epoch a resumed run's shuffles restart their epoch count, so it is a
run of that length with another batch order). A later call into the same --out must extend the lengths
run there before. Resumable: OUT/results.jsonl keeps every
finished (seed, arm, draw, frozen, detector steps); a rerun skips them. Prints one JSON line per detector, then
per seed each arm's mAP@0.5 by draw and the contrastive − regression difference per draw (mean and sd
over draws).

A work directory without its data/ (carried to a GPU machine with only plan.json and the seeds'
pretrain_*/selected bundles) has its training and validation records regenerated from the plan, and a
missing --heldout directory is generated from --heldout-seed.

Measured (session 17, the small report's work directory, 32 held-out records of data seed 7, on a lent
H100): README "Label draws" and docs/findings.md ("Why three fail").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import time
from pathlib import Path

import torch

from core.bundle import load_bundle
from core.data.shards import ShardDataset
from core.device import resolve_device
from core.presets import get_preset
from services.bench import evaluations
from services.bench.plan import BenchConfig
from services.bench.stopping import StageRule
from services.bench.training import train_stage
from services.training.label_subset import labelled_subset


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="a `bench paper` run's REPORT_DIR/work")
    p.add_argument("--heldout", type=Path, required=True, help="records to score on (not the test set)")
    p.add_argument("--heldout-seed", type=int, default=None,
                   help="if --heldout does not exist, generate it: synthetic records of this data seed (e.g. 7)")
    p.add_argument("--heldout-episodes", type=int, default=32)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--arms", nargs="+", choices=("random", "regression", "contrastive"),
                   default=["contrastive", "regression"])
    p.add_argument("--draws", type=int, nargs="+", default=list(range(8)))
    p.add_argument("--budget", type=int, default=None, help="labelled records per draw (default: the plan's smallest)")
    p.add_argument("--max-heldout", type=int, default=None)
    p.add_argument("--pretrain-steps", type=int, default=0)
    p.add_argument("--pretrain-options", type=json.loads, default={})
    p.add_argument("--continue-pretraining", type=int, default=0, metavar="N",
                   help="continue each arm's benchmark pretraining that stopped earlier to N steps")
    p.add_argument("--frozen", action="store_true",
                   help="pretrained arms' detectors on frozen features (the paper's protocol); random stays end to end")
    p.add_argument("--detector-steps", type=int, nargs="+", default=[0],
                   help="train each detector this many fixed steps instead of the plan's rule (0: the rule); "
                        "several (ascending): score each, continuing one run")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)

    if args.pretrain_steps and args.continue_pretraining:
        p.error("--pretrain-steps (a fresh pretraining) and --continue-pretraining exclude each other")
    lengths = args.detector_steps
    if len(lengths) > 1 and (0 in lengths or lengths != sorted(set(lengths))):
        p.error("--detector-steps: several lengths must be positive and ascending")
    config = BenchConfig.from_dict(json.loads((args.work / "plan.json").read_text()))
    config = dataclasses.replace(config, device=str(device))
    _regenerate_missing_data(config, args)
    budget = args.budget or config.budgets_sorted[0]
    batch_size = config.detector_batch_size(budget, get_preset(config.preset).train.batch_size)  # as the benchmark's
    train_dir = args.work / "data" / "train"
    held = ShardDataset(args.heldout)
    heldout = [held[i] for i in range(min(len(held), args.max_heldout or len(held)))]
    val = ShardDataset(args.work / "data" / "val")
    val_records = [val[i] for i in range(len(val))]
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.jsonl"
    rows = [json.loads(line) for line in results_path.read_text().splitlines()] if results_path.exists() else []
    # rows of the other protocol or other detector lengths stay in the file
    rows = [r for r in rows if r.get("frozen", False) == args.frozen and r.get("detector_steps", 0) in lengths]
    # one length: its own run dir (as before); several: one run continued through them
    steps_suffix = ("" if lengths == [0] else f"_s{lengths[0]}") if len(lengths) == 1 else "_continued"
    done = {(r["seed"], r["arm"], r["draw"], r.get("detector_steps", 0)) for r in rows}

    def pretrained(seed: int, arm: str) -> Path | None:
        if arm == "random":
            return None
        if args.continue_pretraining:
            return _continued_pretraining(config, args, seed, arm, train_dir, val_records)
        if not args.pretrain_steps:
            return args.work / f"seed{seed}" / f"pretrain_{arm}" / "selected"
        return train_stage(config, task="pretrain", data_dir=train_dir, run_dir=args.out / f"seed{seed}_pretrain_{arm}",
                           rule=StageRule.fixed(args.pretrain_steps), seed=seed, heldout_records=val_records,
                           task_options={**config.stage_options("pretrain", {"objective": arm}), **args.pretrain_options},
                           log=lambda _: None)

    for draw in args.draws:          # draws outermost: a cut-off run still has every arm of its first draws
        for seed in args.seeds:
            for arm in args.arms:
                frozen = args.frozen and arm != "random"
                run_dir = args.out / f"seed{seed}_{arm}_d{draw}{'_frozen' if frozen else ''}{steps_suffix}"
                for steps in lengths:
                    if (seed, arm, draw, steps) in done:
                        continue
                    started = time.time()
                    labels = labelled_subset(train_dir, run_dir, budget, first=draw * budget)
                    bundle_dir = train_stage(
                        config, task="detector", data_dir=labels, run_dir=run_dir,
                        rule=StageRule.fixed(steps) if steps else config.rules.detector,
                        seed=seed + 100 * draw, heldout_records=val_records,
                        task_options=config.stage_options("detector", {"labels": None, "freeze_features": frozen}),
                        init_bundle=pretrained(seed, arm), freeze=("mapper",) if frozen else (),
                        batch_size=batch_size,
                        log=lambda _: None)
                    bundle = load_bundle(bundle_dir, device)
                    trained = bundle.meta["provenance"]["steps"]
                    if steps and trained != steps:   # the run dir already went further (another list of lengths)
                        raise SystemExit(f"{run_dir} holds a detector trained {trained} steps, not {steps}: give "
                                         "lengths that extend the ones run there before, or a new --out")
                    scores = evaluations.detection(bundle, heldout, device=device)
                    row = {"seed": seed, "arm": arm, "draw": draw, "frozen": args.frozen,
                           "detector_steps": steps, "map": scores["map"],
                           "detections": scores["detections"], "gt": scores["gt_boxes"],
                           "seconds": round(time.time() - started, 1)}
                    rows.append(row)
                    with results_path.open("a") as f:
                        f.write(json.dumps(row) + "\n")
                    print(json.dumps(row), flush=True)
    _summary(rows)


def _continued_pretraining(config: BenchConfig, args, seed: int, arm: str, train_dir: Path,
                           val_records: list[dict]) -> Path:
    """The bundle of seed `seed`'s `arm` pretraining at step --continue-pretraining (see the module docstring)."""
    import shutil

    from services.training.checkpoints import newest_complete_checkpoint

    steps = args.continue_pretraining
    stage = args.work / f"seed{seed}" / f"pretrain_{arm}"
    if json.loads((stage / "stopping.json").read_text())["steps_run"] >= steps:
        return stage / "selected"
    run_dir = args.out / f"seed{seed}_pretrain_{arm}_to{steps}"
    if not (run_dir / "checkpoints").exists():
        newest = newest_complete_checkpoint(stage / "checkpoints")
        if newest is None:
            raise SystemExit(f"{stage}/checkpoints holds no complete checkpoint to continue from")
        staging = run_dir.with_name(run_dir.name + ".tmp")
        shutil.rmtree(staging, ignore_errors=True)
        shutil.copytree(newest, staging / "checkpoints" / newest.name)
        run_dir.mkdir(parents=True, exist_ok=True)
        os.replace(staging / "checkpoints", run_dir / "checkpoints")
        shutil.rmtree(staging)
        print(f"continuing {stage} from {newest.name} to step {steps} in {run_dir}", flush=True)
    return train_stage(config, task="pretrain", data_dir=train_dir, run_dir=run_dir, rule=StageRule.fixed(steps),
                       seed=seed, heldout_records=val_records,
                       task_options=config.stage_options("pretrain", {"objective": arm}), log=lambda _: None)


def _regenerate_missing_data(config: BenchConfig, args) -> None:
    """A work directory carried without its datasets (to a GPU machine: plan.json and the pretrained
    bundles are a few MB, the data 50 MB) gets its training and validation records regenerated from the
    plan with the benchmark's generator and seeds (byte-identical to the benchmark's on the same software:
    checked on the small plan's validation split); --heldout likewise from --heldout-seed. Several processes
    on one work directory: let one generate first (they would write the same directories at once)."""
    from services.bench.data import generate_split
    from services.bench.paper import _data_specs

    specs = _data_specs(config)
    for split in ("train", "val"):
        target = args.work / "data" / split
        if not (target / "manifest.json").exists():
            print(f"regenerating {target} from the plan", flush=True)
            generate_split(target, **specs[split])
    if not (args.heldout / "manifest.json").exists():
        if args.heldout_seed is None:
            raise SystemExit(f"--heldout {args.heldout} does not exist (give --heldout-seed S to generate it)")
        generate_split(args.heldout, preset=config.preset, episodes=args.heldout_episodes, seed=args.heldout_seed,
                       split="val", **({"world": dict(config.world)} if config.world else {}))


def _summary(rows: list[dict]) -> None:
    """Per detector length and seed: each arm's mAP@0.5 by draw, and the contrastive − regression difference
    per draw."""
    for steps in sorted({r.get("detector_steps", 0) for r in rows}):
        at = [r for r in rows if r.get("detector_steps", 0) == steps]
        print(f"detector steps: {steps or 'the plan rule'}")
        for seed in sorted({r["seed"] for r in at}):
            by_arm = {arm: {r["draw"]: r["map"]["0.5"] for r in at if r["seed"] == seed and r["arm"] == arm}
                      for arm in sorted({r["arm"] for r in at})}
            for arm, maps in by_arm.items():
                print(f"seed {seed} {arm:12s} " + " ".join(f"{maps[d]:.3f}" for d in sorted(maps))
                      + f"  mean {statistics.mean(maps.values()):.3f}")
            if {"contrastive", "regression"} <= set(by_arm):
                draws = sorted(set(by_arm["contrastive"]) & set(by_arm["regression"]))
                diff = [by_arm["contrastive"][d] - by_arm["regression"][d] for d in draws]
                sd = statistics.stdev(diff) if len(diff) > 1 else float("nan")
                print(f"seed {seed} contrastive - regression by draw " + " ".join(f"{x:+.3f}" for x in diff)
                      + f"  mean {statistics.mean(diff):+.3f}, sd {sd:.3f} over {len(diff)} draws")


if __name__ == "__main__":
    main()
