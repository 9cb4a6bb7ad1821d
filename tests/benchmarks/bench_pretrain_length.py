"""Does the contrastive arm's early stop cost 3D flow? Flow over a contrastive pretraining continued to N steps.

    python tests/benchmarks/bench_pretrain_length.py --work REPORT_DIR/work --heldout DIR [--heldout-seed 7]
        [--out OUT] [--seeds 0 1 2] [--steps 3000] [--max-heldout 32] [--threads 1]

In a `bench paper` run the plateau rule stops the contrastive pretraining on a noisy held-out loss (its
matching term moves it ±5–10 % between evaluations) after about a third of the steps view regression runs
(small regeneration: 900–1200 against 3000), so the flow claim compares maps of unequal training. Per seed
this continues the benchmark's contrastive pretraining from its newest checkpoint to --steps fixed steps (as
tests/benchmarks/bench_label_draws.py --continue-pretraining: the same options and per-step seeds, so the
run its rule would have made had it let it go on; OUT/seed<s>_pretrain_contrastive_to<N>/checkpoints seeded
by hand with a later checkpoint of the same run, e.g. of a shorter continuation, resumes from it), trains flow over its frozen features exactly as the benchmark's flow stage does (the plan's flow
rule and `flow_features` options, `services.bench.training.train_stage`), and scores it beside the benchmark's
own contrastive and regression flows with the benchmark's flow protocol (`core.eval.protocols.flow`, moving
threshold 1e-3 voxel) on DIR's records — use records that are not the benchmark's test set. A seed whose
continued pretraining would not be longer than the benchmark's is skipped.

Resumable: every stage resumes from its checkpoints, and OUT/results.jsonl keeps each scored (seed, row); a
rerun skips them. Prints one JSON line per row (moving-voxel L1 EPE of the gated, filled and raw flow, and
zero motion), then per seed the contrastive − regression differences.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling benchmark's helpers
from bench_label_draws import _continued_pretraining, _regenerate_missing_data  # noqa: E402

from core.bundle import load_bundle  # noqa: E402
from core.data.shards import ShardDataset  # noqa: E402
from core.device import resolve_device  # noqa: E402
from core.eval.protocols import flow as flow_protocol  # noqa: E402
from services.bench.plan import BenchConfig  # noqa: E402
from services.bench.training import train_stage  # noqa: E402

ROWS = ("model", "model_filled", "model_raw", "zero_motion")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, required=True, help="a `bench paper` run's REPORT_DIR/work")
    p.add_argument("--heldout", type=Path, required=True, help="records to score on (not the test set)")
    p.add_argument("--heldout-seed", type=int, default=None, help="data seed to generate --heldout from if missing")
    p.add_argument("--heldout-episodes", type=int, default=32)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=3000, help="continue the contrastive pretraining to this step")
    p.add_argument("--max-heldout", type=int, default=32)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    config = dataclasses.replace(BenchConfig.from_dict(json.loads((args.work / "plan.json").read_text())),
                                 device=str(device))
    args.continue_pretraining = args.steps       # what _continued_pretraining reads
    _regenerate_missing_data(config, args)
    train_dir = args.work / "data" / "train"
    val = ShardDataset(args.work / "data" / "val")
    val_records = [val[i] for i in range(len(val))]
    held = ShardDataset(args.heldout)
    heldout = [held[i] for i in range(min(len(held), args.max_heldout))]
    args.out.mkdir(parents=True, exist_ok=True)
    results = args.out / "results.jsonl"
    rows = [json.loads(line) for line in results.read_text().splitlines()] if results.exists() else []
    done = {(r["seed"], r["row"]) for r in rows}
    print(f"command: python {' '.join(sys.argv)} | load {os.getloadavg()[0]:.2f} | {len(heldout)} records of "
          f"{args.heldout}", flush=True)

    for seed in args.seeds:
        stage = args.work / f"seed{seed}"
        ran = json.loads((stage / "pretrain_contrastive" / "stopping.json").read_text())["steps_run"]
        if ran >= args.steps:
            print(f"seed {seed}: the benchmark's contrastive pretraining already ran {ran} steps; skipped", flush=True)
            continue
        flows = {"contrastive (benchmark)": stage / "flow_contrastive" / "selected",
                 "regression (benchmark)": stage / "flow_regression" / "selected",
                 f"contrastive to {args.steps}": None}
        for name, flow_dir in flows.items():
            if (seed, name) in done:
                continue
            started = time.time()
            if flow_dir is None:   # the continued pretraining, then flow over its frozen features as the bench does
                pretrained = _continued_pretraining(config, args, seed, "contrastive", train_dir, val_records)
                flow_dir = train_stage(config, task="flow", data_dir=train_dir,
                                       run_dir=args.out / f"seed{seed}_flow_contrastive_to{args.steps}",
                                       rule=config.rules.flow, seed=seed, heldout_records=val_records,
                                       task_options=config.stage_options("flow_features", {"inputs": "features"}),
                                       init_bundle=pretrained, freeze=("mapper",), log=lambda _: None)
            bundle = load_bundle(flow_dir, device)
            scores = flow_protocol.evaluate(bundle, heldout, device=device, moving_threshold=1e-3)["scores"]
            stopping = json.loads((flow_dir.parent / "stopping.json").read_text())
            row = {"seed": seed, "row": name, "steps": args.steps,
                   "flow_steps_run": stopping["steps_run"], "flow_selected": stopping["selected_step"],
                   **{f"epe_moving_{r}": scores[r]["epe_l1_moving"] for r in ROWS},
                   **{f"epe_static_{r}": scores[r]["epe_l1_static"] for r in ROWS if r != "zero_motion"},
                   "seconds": round(time.time() - started, 1), "load": round(os.getloadavg()[0], 2)}
            rows.append(row)
            with results.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    _summary(rows, args.steps)


def _summary(rows: list[dict], steps: int) -> None:
    by = {(r["seed"], r["row"]): r for r in rows}
    print("\nmoving-voxel L1 EPE (gated / filled / raw); contrastive − regression (negative: contrastive better)")
    for seed in sorted({r["seed"] for r in rows}):
        line = [f"seed {seed}"]
        reg = by.get((seed, "regression (benchmark)"))
        for name in ("contrastive (benchmark)", f"contrastive to {steps}", "regression (benchmark)"):
            r = by.get((seed, name))
            if r is None:
                continue
            figures = " / ".join(f"{r[f'epe_moving_{k}']:.3f}" for k in ("model", "model_filled", "model_raw"))
            diff = "" if reg is None or r is reg else " (" + " / ".join(
                f"{r[f'epe_moving_{k}'] - reg[f'epe_moving_{k}']:+.3f}" for k in ("model", "model_filled", "model_raw")) + ")"
            line.append(f"{name} {figures}{diff}")
        print("; ".join(line))


if __name__ == "__main__":
    main()
