"""`n3dmap bench paper`: generate data, pretrain, train the downstream modules, evaluate, and report;
`n3dmap bench status`: how far a run is (services/bench/status.py);
`n3dmap bench carry save|restore`: carry a benchmark's work to another machine (services/bench/carry.py).

    n3dmap bench paper --preset small --out REPORT_DIR [--seeds 3] [--parallel-seeds N] [--quick]
    n3dmap bench status --out REPORT_DIR [--json]
    n3dmap bench carry save --out REPORT_DIR --to CARRY_DIR
    n3dmap bench carry restore --from CARRY_DIR --out REPORT_DIR

Everything lands in REPORT_DIR: report.md, metrics.json and PNG plots at the top, every stage's
dataset, run and metrics under REPORT_DIR/work/. Rerunning the same command continues a cut-off run
(finished stages are skipped, a training stage resumes from its last checkpoint); `--rerun-changed`
continues it under a changed plan, redoing only the stages the change touches (services/bench/replan.py), and
`--redo PATTERN` redoes the named stages and what reads them (after a code change). See
services/bench/paper.py for the stages and services/bench/plan.py for the per-preset plans.
"""

from __future__ import annotations

import argparse
import json

from services.cli.paths import check_creatable_dir

# Training stages with a stopping rule, each with its --<stage>-steps flag (services.bench.plan.STAGE_NAMES;
# kept here so that building the parser does not import torch).
STAGE_NAMES = ("pretrain", "occupancy", "detector", "flow", "egomotion")

def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _budget(text: str):
    if text == "all":
        return None
    return _positive_int(text)


def register(subparsers) -> None:
    bench = subparsers.add_parser("bench", help="benchmarks that reproduce the paper's tables on the synthetic world",
                                  description="Benchmarks that reproduce the paper's tables on the synthetic world.")
    kinds = bench.add_subparsers(dest="bench_kind", metavar="KIND", required=True)
    p = kinds.add_parser(
        "paper", help="the paper's experiments end to end: data, pretraining, downstream modules, report",
        description="Generate synthetic data, pretrain (view-contrastive and view-regression; random init as the "
                    "third arm), train the detector at several label budgets (--detector-variants), 3D flow and "
                    "egomotion, evaluate everything and write REPORT_DIR/report.md, metrics.json and plots. "
                    "Rerunning continues a cut-off run.")
    p.add_argument("--preset", default="small", choices=("tiny", "small", "paper"), help="model/grid/data preset")
    p.add_argument("--out", required=True, metavar="REPORT_DIR", help="report and work directory (created)")
    p.add_argument("--seeds", type=_positive_int, default=3, metavar="N",
                   help="train every model with N seeds (0..N-1; default 3, the fewest a verdict needs); the report "
                        "shows mean ± std and each seed's value")
    p.add_argument("--parallel-seeds", type=_positive_int, default=None, metavar="N",
                   help="seeds trained at once, each in its own process (default: one per seed, at most the usable CPUs). The "
                        "CPUs are shared out; more processes than CPUs run one thread each, time-sliced (e.g. 3 "
                        "seeds on 2 CPUs: all end together, instead of the last seed alone on one CPU)")
    p.add_argument("--quick", action="store_true",
                   help="test profile: a few records and steps per stage (checks the pipeline, not the paper)")
    p.add_argument("--train-episodes", type=_positive_int, default=None, metavar="N", help="training records")
    p.add_argument("--test-episodes", type=_positive_int, default=None, metavar="N", help="test records")
    p.add_argument("--label-budgets", type=_budget, nargs="+", default=None, metavar="N|all",
                   help="labelled training records for the detector, e.g. 2 8 32 all")
    p.add_argument("--label-draws", type=_positive_int, default=None, metavar="K",
                   help="train the smallest budget's detectors on K disjoint label sets (records [d*N, (d+1)*N)) and "
                        "report their mean (default: the preset's plan: small 4, paper 4, tiny 1)")
    p.add_argument("--detector-variants", type=_variant, nargs="+", default=None, metavar="ARM/MODE",
                   help="the detector rows to train, ARM one of random, regression, contrastive and MODE frozen or "
                        "finetuned, e.g. random/finetuned regression/frozen contrastive/frozen contrastive/finetuned "
                        "(default: the preset's plan: small the rows the claims read, the paper's protocol; tiny "
                        "and paper every pretrained arm frozen and fine-tuned too)")
    steps = p.add_argument_group("training length (default: each stage's stopping rule in the preset's plan)")
    for stage in STAGE_NAMES:
        steps.add_argument(f"--{stage}-steps", type=_positive_int, default=None, metavar="N",
                           help=f"train the {stage} stage for exactly N steps instead of its stopping rule")
    p.add_argument("--batch-size", type=_positive_int, default=None, help="records per step (default: preset)")
    p.add_argument("--data-seed", type=int, default=0, help="seed of the synthetic train set (test: +1)")
    p.add_argument("--workers", type=int, default=0,
                   help="0 (default): train in this process; N: Ray Train with N workers per stage")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    p.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                   help="every training stage's `n3dmap train --precision` (default fp32; see its help)")
    p.add_argument("--threads", type=_positive_int, default=None,
                   help="torch threads per process instead of the plan's share of the CPUs (may oversubscribe)")
    p.add_argument("--task-options", type=_json_object, default=None, metavar="JSON",
                   help='extra task options per kind of stage, e.g. \'{"mapper": {"encoder_full_res": 16}, '
                        '"pretrain": {"coeff_match": 1.0}, "flow_features": {"refine_radius": [3, 1, 3]}}\' '
                        '(kinds: mapper, pretrain, occupancy, detector, flow_features, flow_volume; every arm '
                        'gets the same options, but pretrain_contrastive takes the contrastive objective\'s own '
                        'shift_positives / coeff_local_negatives / local_negative_radius; default: none)')
    p.add_argument("--world", type=_json_object, default=None, metavar="JSON",
                   help='synthetic world fields changed for all three datasets, e.g. camera photometrics '
                        '\'{"exposure_std": 0.3, "white_balance_std": 0.1, "pixel_noise_std": 0.03}\' or '
                        '\'{"texture_scale": [0.1, 0.4]}\' (core.synthetic.config.WorldConfig; default: the '
                        "preset's world)")
    p.add_argument("--rerun-changed", action="store_true",
                   help="REPORT_DIR may hold a benchmark of another plan: redo only the stages the change "
                        "touches (their settings or inputs differ) and keep the rest; without it a changed "
                        "plan is refused")
    p.add_argument("--redo", nargs="+", default=(), metavar="PATTERN",
                   help="redo the stages whose names match a shell-style PATTERN (e.g. 'seed*/egomotion', "
                        "'seed*/eval/occupancy/*'; names as in the report's stage table) and every stage that reads "
                        "their output: what a code change needs, since stages are keyed by their settings, not "
                        "the code")
    p.set_defaults(func=run)

    status = kinds.add_parser(
        "status", help="how far a bench paper run is: finished stages, those under way (at which step), what runs next",
        description="Read REPORT_DIR/work and its plan, run nothing, and print every seed's finished stages, the "
                    "stages under way (a training stage: the step of the checkpoint it resumes from) and the "
                    "next stage to run, with the stage time spent so far (services/bench/status.py).")
    status.add_argument("--out", required=True, metavar="REPORT_DIR", help="the --out of the `bench paper` run")
    status.add_argument("--json", action="store_true", help="print the status as JSON, one entry per stage")
    status.set_defaults(func=run_status)

    carry = kinds.add_parser(
        "carry", help="carry a benchmark's work to another machine: save what cannot be remade, restore it",
        description="Save the part of a `bench paper` work directory that cannot be remade (trained stages' "
                    "bundles and logs, evaluations, the newest checkpoint of a stage under way) into a folder "
                    "git can hold, or rebuild a work directory from such a folder on another machine (the "
                    "datasets regenerated and checked against the saved checksums). Stop `bench paper` before "
                    "saving. services/bench/carry.py says what is left out and why.")
    actions = carry.add_subparsers(dest="carry_action", metavar="ACTION", required=True)
    save = actions.add_parser("save", help="write REPORT_DIR/work's irreproducible part into CARRY_DIR (replaced)")
    save.add_argument("--out", required=True, metavar="REPORT_DIR", help="the --out of the `bench paper` run")
    save.add_argument("--to", required=True, metavar="CARRY_DIR", help="folder to write (an earlier carry there is replaced)")
    save.set_defaults(func=run_carry_save)
    restore = actions.add_parser("restore", help="rebuild REPORT_DIR/work from CARRY_DIR, then rerun `bench paper`")
    restore.add_argument("--from", dest="source", required=True, metavar="CARRY_DIR", help="a folder written by `bench carry save`")
    restore.add_argument("--out", required=True, metavar="REPORT_DIR",
                         help="the --out the `bench paper` command will be given (its work/ must not exist yet)")
    restore.set_defaults(func=run_carry_restore)


def run_status(args: argparse.Namespace) -> int:
    from services.bench.status import bench_status, format_status

    status = bench_status(args.out)
    print(json.dumps(status, indent=1) if args.json else format_status(status, args.out))
    return 0


def run_carry_save(args: argparse.Namespace) -> int:
    from services.bench.carry import save_carry

    check_creatable_dir(args.to, "--to")
    save_carry(args.out, args.to)
    return 0


def run_carry_restore(args: argparse.Namespace) -> int:
    from services.bench.carry import restore_carry

    check_creatable_dir(args.out, "--out")
    restore_carry(args.source, args.out)
    return 0


def _variant(text: str) -> tuple[str, str]:
    """--detector-variants: ARM/MODE (checked further by BenchConfig)."""
    arm, sep, mode = text.partition("/")
    if not sep or not arm or not mode:
        raise argparse.ArgumentTypeError(f"{text!r} is not ARM/MODE, e.g. contrastive/frozen")
    return arm, mode


def _json_object(text: str) -> dict:
    """--task-options / --world: a JSON object (checked further by BenchConfig)."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"not JSON ({e.msg} at character {e.pos})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError("must be a JSON object")
    return value


def config_from_args(args: argparse.Namespace):
    from services.bench.plan import plan_for, with_steps

    overrides = {k: v for k, v in {
        "train_episodes": args.train_episodes, "test_episodes": args.test_episodes,
        "label_budgets": tuple(args.label_budgets) if args.label_budgets else None,
        "label_draws": args.label_draws,
        "detector_variants": tuple(args.detector_variants) if args.detector_variants else None,
        "batch_size": args.batch_size, "task_options": args.task_options, "world": args.world}.items()
        if v is not None}
    config = plan_for(args.preset, seeds=tuple(range(args.seeds)), quick=args.quick, data_seed=args.data_seed,
                      workers=args.workers, device=args.device, precision=args.precision, **overrides)
    steps = {s: getattr(args, f"{s}_steps") for s in STAGE_NAMES}
    steps = {k: v for k, v in steps.items() if v is not None}
    return with_steps(config, **steps) if steps else config


def run(args: argparse.Namespace) -> int:
    import signal

    from services.bench.paper import run_paper_bench
    from services.threads import usable_cpus
    from services.training.stop_signal import raise_keyboard_interrupt

    # SIGTERM stops the run as Ctrl-C does: its seed workers are told to stop and waited for (each saves a
    # checkpoint at its step), its pid file goes; without this the process died at once and left both to chance.
    # A training stage in this process takes SIGTERM over while it trains (services/training/stop_signal.py).
    signal.signal(signal.SIGTERM, raise_keyboard_interrupt)
    config = config_from_args(args)
    check_creatable_dir(args.out, "--out")
    parallel = args.parallel_seeds if args.parallel_seeds is not None else min(len(config.seeds), usable_cpus())
    metrics = run_paper_bench(config, args.out, parallel_seeds=parallel, threads=args.threads,
                              rerun_changed=args.rerun_changed, redo=tuple(args.redo))
    for claim in metrics["claims"]:
        print(f"  {claim['id']}: {claim['verdict']} ({claim['reason']}; {claim['ours']})")
    return 0
