"""The benchmark report: OUT/report.md, OUT/metrics.json and PNG plots, through services.reports.Report.

Sections, in the paper's order: semi-supervised detection (mAP vs number of labels per pretraining,
frozen and fine-tuned; the mAP@{0.33,0.5,0.75} table), retrieval P@1/5/10 (2D and 3D), flow EPE
(full/static/moving with the zero-motion row), moving-object PR curves (static camera, moving camera,
2.5D baselines), occupancy accuracy, egomotion vs ICP, then the claims, the learned chain's targets
(services.bench.targets), the stopping rules, then the stages' wall times.
Every number is the mean over seeds, with ± the (population) standard deviation when there are several.
metrics.json's "metrics" holds the same tables (mean/std/n/values per cell), the claims, the config,
the seeds, the wall times and the raw per-seed results.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from services.bench import aggregate as agg
from services.bench.claims import check_claims
from services.bench.claims import ABSOLUTE_TARGETS
from services.bench.targets import check_targets
from services.bench.judge import FLOORS, MIN_SEEDS, seed_key
from services.bench.plan import OCCUPANCY_ROWS, PRETRAINED_ARMS, BenchConfig
from services.reports import Report

METRIC_KEYS = ("config", "seeds", "wall_time_s", "stage_seconds", "stage_code", "total_stage_seconds", "detection",
               "retrieval", "flow", "moving", "occupancy", "egomotion", "claims", "targets", "per_seed", "stopping")


def _budget_names(config: BenchConfig) -> list[str]:
    return ["all" if b is None else str(b) for b in config.budgets_sorted]


def build_tables(config: BenchConfig, per_seed: dict) -> dict:
    return {
        "detection": agg.detection_table(per_seed, config.detector_variants, _budget_names(config)),
        "retrieval": agg.retrieval_table(per_seed, ("random", *PRETRAINED_ARMS)),
        "flow": agg.flow_table(per_seed, PRETRAINED_ARMS),
        "moving": agg.moving_table(per_seed),
        "occupancy": agg.occupancy_table(per_seed, OCCUPANCY_ROWS),
        "egomotion": agg.egomotion_table(per_seed),
    }


def write_bench_report(out: Path, *, config: BenchConfig, results: dict, stage_seconds: dict,
                       wall_time_s: float, ran: list[str], stopping: dict | None = None,
                       stage_code: dict[str, list[str]] | None = None) -> dict:
    """Write the report into `out`; returns the metrics dict written under "metrics". stage_code: stage -> the
    commits its attempts ran (StageRunner.code; [] where not recorded)."""
    stage_code = stage_code or {}
    per_seed = results["seeds"]
    tables = build_tables(config, per_seed)
    budgets = _budget_names(config)
    claims = check_claims(per_seed, budgets=budgets, variants=[f"{a}/{m}" for a, m in config.detector_variants],
                          quick=config.quick)
    targets = check_targets(per_seed, quick=config.quick)
    total_stages = sum(v for v in stage_seconds.values() if isinstance(v, float) and math.isfinite(v))

    report = Report(kind="bench_paper", title=f"Paper benchmark on the synthetic world ({config.preset} preset)",
                    data=str(out / "work" / "data"),
                    settings={"preset": config.preset, "seeds": list(config.seeds), "profile": "quick" if config.quick else "full",
                              "train_records": config.train_episodes, "test_records": config.test_episodes,
                              "validation_records": config.val_episodes,
                              "label_budgets": budgets, "stopping_rules": {k: r.describe() for k, r in vars(config.rules).items()},
                              # shown only when not the default, so fp32 reports read as before
                              **({"training_precision": config.precision} if config.precision != "fp32" else {}),
                              **({"synthetic_world": dict(config.world)} if config.world else {}),
                              # the recipe (services.bench.plan: task_options), so the report says what it ran
                              **({"task_options": dict(config.task_options)} if config.task_options else {}),
                              "wall_time_this_run_s": round(wall_time_s, 1), "wall_time_all_stages_s": round(total_stages, 1)})
    report.text(f"Every number is the mean over {len(config.seeds)} seed(s) {list(config.seeds)}"
                + (" ± the standard deviation over seeds (population: divided by the number of seeds)"
                   if len(config.seeds) > 1 else " (one seed: no spread)")
                + ". Seeds change the weights' initialisation and the data order; the synthetic train/test data "
                f"are shared (data seed {config.data_seed}, test seed {config.data_seed + 1}, validation seed "
                f"{config.data_seed + 2}). How long each stage trains is its stopping rule's call (section "
                "'Training: stopping rules and steps run')." + (" **Quick profile: the numbers only show the pipeline "
                                                        "runs; they say nothing about the paper.**" if config.quick else ""))

    _detection_section(report, tables["detection"], config, budgets, per_seed)
    _retrieval_section(report, tables["retrieval"])
    _flow_section(report, tables["flow"])
    _moving_section(report, tables["moving"], config)
    _occupancy_section(report, tables["occupancy"])
    _egomotion_section(report, tables["egomotion"])
    _claims_section(report, claims, config)
    _targets_section(report, targets, config)
    _stopping_section(report, config, stopping or {})
    _stages_section(report, stage_seconds, ran, wall_time_s, total_stages, stage_code)

    report.metrics = {
        "config": config.to_dict(), "seeds": list(config.seeds), "wall_time_s": wall_time_s,
        "stage_seconds": stage_seconds, "stage_code": stage_code, "total_stage_seconds": total_stages, **tables,
        "claims": claims, "targets": targets,
        "per_seed": per_seed, "stopping": stopping or {},
    }
    report.write(out)
    return report.metrics


# ----------------------------------------------------------------------------- sections

def _detection_section(report: Report, det: dict, config: BenchConfig, budgets: list[str], per_seed: dict) -> None:
    report.heading("Semi-supervised 3D object detection: mAP vs number of labels")
    report.text("A Faster-RCNN-style 3D detector trained on the latent map with box labels from N training records "
                "(`all` = every one), on features from random init, view-regression or view-contrastive "
                "pretraining, frozen or fine-tuned. mAP over the test set at 3D IoU 0.5 (axis-aligned boxes, "
                "all-point AP).")
    report.table(["pretraining / features", *[f"N={b}" for b in budgets]],
                 [[v, *[agg.fmt(det[v][b]["0.5"]) for b in budgets]] for v in det])
    few = config.budgets_sorted[0]
    draws = config.draws_of(few)
    if draws > 1:
        report.text(f"At N={few} every detector is trained on {draws} disjoint label sets (draw d: training records "
                    f"d·{few} to (d+1)·{few} − 1) and each N={few} cell is the mean over the draws: one set of {few} "
                    "records is too few to tell the arms apart by a margin of 0.02. mAP@0.5 by draw (mean ± std over "
                    "seeds), and the differences per draw (the few-label claims read the frozen pretrained "
                    "arms against random init trained end to end, the paper's protocol):")
        by_draw = agg.detection_draws_table(per_seed, config.detector_variants, str(few), draws)
        report.table(["pretraining / features", *[f"draw {d}" for d in range(draws)]],
                     [[v, *[agg.fmt(s) for s in row]] for v, row in by_draw.items()])
    for b in (budgets[0], budgets[-1]):
        report.text(f"mAP at IoU 0.33 / 0.5 / 0.75 with N={b} labelled records (the paper's transfer table layout):")
        report.table(["method", "mAP@0.33", "mAP@0.5", "mAP@0.75"],
                     [[v, *[agg.fmt(det[v][b][i]) for i in ("0.33", "0.5", "0.75")]] for v in det])
    x = [config.budget_records(b) for b in config.budgets_sorted]
    fig = Figure(figsize=(13, 3.6))
    axes = fig.subplots(1, 3)
    for ax, iou in zip(axes, ("0.33", "0.5", "0.75")):
        for v in det:
            mean = [det[v][b][iou]["mean"] for b in budgets]
            std = [det[v][b][iou]["std"] or 0.0 for b in budgets]
            mean = [np.nan if m is None else m for m in mean]
            ax.errorbar(x, mean, yerr=std, marker="o", capsize=3, label=v,
                        linestyle="--" if v.endswith("frozen") else "-")
        ax.set_xscale("log", base=2)
        ax.set_xlabel("labelled training records")
        ax.set_ylabel(f"mAP@{iou}")
        ax.set_title(f"3D IoU {iou}")
        ax.set_ylim(bottom=0)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    report.figure("detection_map_vs_labels", fig,
                  "Detection mAP vs number of labelled records per pretraining (dashed: frozen features)")


def _retrieval_section(report: Report, ret: dict) -> None:
    report.heading("2D and 3D patch retrieval")
    report.text("Precision at rank K: each query patch (2D: projector render of the target view from the other "
                "views; 3D: feature cube of the map of one view, view 0) ranks every candidate of the pool (2D: "
                "bottom-up features of the target image, or the image itself for the regression model; 3D: cubes "
                "of the map fused from the other views) by L2 distance; one candidate is its true correspondence.")
    report.table(["pretraining", "2D P@1", "2D P@5", "2D P@10", "3D P@1", "3D P@5", "3D P@10"],
                 [[arm, *[agg.fmt(ret[arm][d][k]) for d in ("2d", "3d") for k in ("p@1", "p@5", "p@10")]]
                  for arm in ret])


def _flow_section(report: Report, flow: dict) -> None:
    report.heading("3D flow: mean endpoint error in egomotion-stabilised scenes")
    report.text("L1 endpoint error in voxels (test pairs, stabilised with the true poses), over all voxels, "
                "static voxels and moving voxels; the paper's protocol: flow trained over the frozen features "
                "of each pretraining (rows contrastive and regression), free voxels zeroed by the occupancy head. "
                "The row 'input volumes' is n3dmap's default flow module, which compares the fused "
                "occupancy+RGB input volumes instead of feature maps (README: small feature maps do not carry "
                "object motion); the zero-motion row predicts no motion anywhere. Each model row's gate is its own "
                "bundle's occupancy head (for an arm: its pretraining's), so the gated rows (the claims' and the "
                "pipelines') compare the gates as much as the flow modules: the rows 'filled gate' (flow kept within "
                "one voxel of an occupied moving voxel) and 'no gate' compare the flow modules more directly.")
    report.table(["method", "full", "static", "moving", "EPE3D (occupied)"],
                 [[row, *[agg.fmt(flow[row][c]) for c in ("full", "static", "moving", "epe3d")]] for row in flow])


def _moving_section(report: Report, mov: dict, config: BenchConfig) -> None:
    report.heading("Unsupervised 3D moving-object detection")
    report.text(f"AP at 3D IoU {config.moving_iou} (oriented boxes) of the moving objects of each test pair, "
                f"split by camera: static-camera pairs {agg.fmt(mov['pairs_static'], 0)}, moving-camera pairs "
                f"{agg.fmt(mov['pairs_moving'], 0)}. Ours: 3D flow over each pretraining's features, or over the "
                "input volumes (n3dmap's default), stabilised with the true poses or with the egomotion module; 2.5D: 2D optical flow (Farneback; "
                "or the true 2D flow for the oracle), thresholded, clustered, lifted with depth, per view. Every "
                "method's boxes are completed to whole objects the same way (a size prior each estimates from its own "
                "components, no labels, the 2.5D ones from their stabilised variant's; split, grown away from the "
                "camera, down to the ground) — only the 3D methods also take a heading from coherent 3D flow.")
    for setting in ("static", "moving"):
        rows = [[m, agg.fmt(v["ap"]), agg.fmt(v.get("ap_iou025")), agg.fmt(v["gt_boxes"], 0)]
                for m, v in mov[setting].items()]
        report.text(f"{setting.capitalize()} camera:")
        report.table(["method", f"AP@{config.moving_iou}", "AP@0.25", "moving objects"], rows)
        fig = Figure(figsize=(5, 4))
        ax = fig.subplots()
        for m, v in mov[setting].items():
            curve = v.get("curve") or {}
            if curve.get("recall"):
                ax.plot(curve["recall"], curve["precision"], marker=".", label=f"{m} (AP {agg.fmt(v['ap'], 2)})")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_title(f"Moving objects, {setting} camera (first seed)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        report.figure(f"moving_pr_{setting}_camera", fig, f"Moving-object PR curves, {setting} camera")


def _occupancy_section(report: Report, occ: dict) -> None:
    report.heading("Occupancy accuracy")
    report.text("Map from one view; labels from that view and the next (occupied: points; free: ray traversal); "
                "unlabelled voxels ignored. The occupancy module is trained the same way (`n3dmap train "
                "occupancy`: a map of one random view, labels from it and one other view), mapper fine-tuned from "
                "the contrastive pretraining; the claim reads it at the balanced threshold: the one (of 0.05, 0.10, "
                "…, 0.95) whose worse class accuracy is highest on the validation records, each of their views taken "
                "as the input in turn, then applied to the test records (at 0.5 beside it). Each pretraining also "
                "trains its own head, on maps fused from all views but one; those heads are the other columns, at "
                "0.5.")
    names = {"acc_occupied": "Occupied space", "acc_free": "Free space", "acc_all": "All space",
             "iou_occupied": "Occupied IoU", "threshold": "Threshold (balanced: chosen on the validation records)"}
    report.table(["3D area type", *occ], [[label, *[agg.fmt(occ[a][k]) for a in occ]] for k, label in names.items()])


def _egomotion_section(report: Report, ego: dict) -> None:
    report.heading("Egomotion error")
    report.text("Relative pose error of ref0_T_ref1 on the moving-camera test pairs: the trained egomotion module, "
                "point-to-plane ICP on the two depth clouds, and the identity (no motion). The module's last stage "
                "has no weights (core/models/egomotion_fine.py; modules trained since session 25: frame 1's depth "
                "points aligned with frame 0's TSDF on a grid 4× finer than the map's) and starts where its learned "
                "stages end; the row \"model, learned stages only\" is that starting point. The \"untrained "
                "module\" rows are the same module before training, with the same last stage: what training "
                "adds is the difference between the two.")
    report.table(["method", "R (rad)", "t (m)", "pairs"],
                 [[m, agg.fmt(v["rot_rad"], 4), agg.fmt(v["trans_m"], 4), agg.fmt(v["pairs"], 0)] for m, v in ego.items()])


def _claims_section(report: Report, claims: list[dict], config: BenchConfig) -> None:
    report.heading("Claims")
    if config.quick:
        report.text("**No verdicts: this is the quick profile**, whose few training steps per stage show that the "
                    "pipeline runs and say nothing about the paper. Each claim's numbers are listed; metrics.json "
                    "records `holds: null` for every claim.")
    else:
        report.text(f"Each claim is judged seed by seed (seeds paired: each seed's models are compared with each "
                    f"other). A claim **holds** only when there are at least {MIN_SEEDS} seeds and every seed shows "
                    "the paper's direction by at least the metric's floor; it **does not hold** when a seed does "
                    "not; it is **undetermined** when there are fewer seeds, a number is missing, both sides "
                    "of a comparison lie below the metric's floor of meaning (e.g. two APs under 0.05), the values "
                    "a comparison needs room above are saturated, or an untrained control meets the claim too.")
        report.table(["metric", "margin (least difference that counts)", "floor of meaning"],
                     [[f.name, f"{f.margin:g}", "–" if f.meaning is None else f"both < {f.meaning:g}"]
                      for f in FLOORS.values()])
        report.text("Absolute targets and tolerances, each its own floor: " + "; ".join(ABSOLUTE_TARGETS) + ".")
    for c in claims:
        report.text(f"- **{c['id']}: {c['verdict']}** ({c['reason']}). {c['claim']} Criterion: {c['criterion']}. "
                    f"Ours (mean ± std [per seed]): {c['ours']}. Paper: {c['paper']}.")
    seeds = sorted({s for c in claims for s in c["outcomes"]}, key=seed_key)
    report.table(["claim", "verdict", *[f"seed {s}" for s in seeds]],
                 [[c["id"], c["verdict"], *[" / ".join(c["outcomes"].get(s, ["–"])) for s in seeds]] for c in claims])
    if not config.quick:
        held = sum(c["holds"] is True for c in claims)
        report.text(f"{held} of {len(claims)} claims hold. Per-seed cells list each condition's outcome: agree, "
                    "disagree, vacuous (below the floor of meaning, saturated, or met by the untrained control too) "
                    "or missing.")


def _targets_section(report: Report, targets: list[dict], config: BenchConfig) -> None:
    report.heading("The learned chain's targets")
    report.text("The bars the project set the learned chain on this benchmark (services/bench/targets.py), beside "
                f"the paper's claims: each is met only when every seed meets it and there are at least {MIN_SEEDS} "
                "seeds; 'no' when a seed misses it, however few seeds there are; 'undetermined' when a number is "
                "missing or there are fewer seeds. A value at a limit passes."
                + (" **Quick profile: not judged.**" if config.quick else ""))
    seeds = sorted({s for t in targets for s in t["per_seed"]}, key=lambda s: (not s.isdigit(), int(s) if s.isdigit() else s))
    verdict = {True: "met", False: "no", None: "undetermined"}
    report.table(["target", "criterion", "met", *[f"seed {s}" for s in seeds]],
                 [[t["id"], t["criterion"], "–" if config.quick else verdict[t["met"]],
                   *[t["per_seed"].get(s, "–") for s in seeds]] for t in targets])


def _stopping_section(report: Report, config: BenchConfig, stopping: dict) -> None:
    report.heading("Training: stopping rules and steps run")
    report.text("Each stage trains by its rule; plateau rules score the task's own loss on the validation records "
                f"({config.val_episodes}, never the test set) and keep the best evaluation's weights (the best moves "
                "only on a drop by the rule's margin).")
    report.table(["stage", "rule"], [[name, rule.describe()] for name, rule in vars(config.rules).items()])
    rows = []
    for seed, stages in stopping.items():
        for stage, info in sorted(stages.items()):
            rows.append([seed, stage, info.get("steps_run"), info.get("selected_step"), info.get("reason", "")])
    if rows:
        report.text("Steps each stage actually ran, the step whose weights it kept, and why it stopped:")
        report.table(["seed", "stage", "steps run", "kept step", "why it stopped"], rows)


def _stages_section(report: Report, seconds: dict, ran: list[str], wall: float, total: float,
                    code: dict[str, list[str]]) -> None:
    report.heading("Stages and wall time")
    report.text(f"This invocation: {wall:.1f} s. All stages (including ones finished by an earlier invocation): "
                f"{total:.1f} s. Stages rerun by this invocation: {len(ran)} of {len(seconds)}. "
                "Code: the git commit(s) each stage's attempts ran at (? for attempts that ran before commits were "
                "recorded).")
    report.table(["stage", "seconds", "this run", "code"],
                 [[name, s, "yes" if name in ran else "earlier", ", ".join(c[:9] for c in code.get(name, ["?"]))]
                  for name, s in seconds.items()], digits=1)
