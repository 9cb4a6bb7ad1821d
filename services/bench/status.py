"""`n3dmap bench status`: how far a `bench paper` run is, read from its work directory without running anything.

The plan (OUT/work/plan.json) is walked dry (services.bench.replan's `StageRunner(dry=True)`), which names every
stage the run has, in the order a seed runs them; each stage is then
- finished: its completion marker exists (a dataset's manifest.json, a training run's stopping.json, an
  evaluation's metrics.json: services.bench.stages);
- under way: its directory exists without the marker (a training stage: the step of the checkpoint it resumes
  from, and its rule's bound);
- to run: no directory yet.
Times: each finished stage's stage.json, and what stopped attempts of a stage under way left in its
stage.partial.json (the seconds of an attempt still running are not on disk until it stops).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from core.errors import N3dmapError
from services.bench.stages import PARTIAL

DATA_MARKER, TRAIN_MARKER, EVAL_MARKER = "manifest.json", "stopping.json", "metrics.json"
# A training stage's rule (services.bench.plan.StageRules field) by its name's first word.
RULE_OF_PREFIX = {"pretrain": "pretrain", "detector": "detector", "flow": "flow", "egomotion": "egomotion",
                  "occupancy": "occupancy"}


class BenchStatusError(N3dmapError):
    """No benchmark (or an unreadable one) where a status was asked for."""


def marker_of(stage: str) -> str:
    """The file whose presence says stage `stage` (a name as in the report's stage table) is finished."""
    if stage.startswith("data/"):
        return DATA_MARKER
    return EVAL_MARKER if "/eval/" in f"/{stage}" else TRAIN_MARKER


def bench_status(out_dir: str | Path) -> dict:
    """{"plan": {preset, seeds}, "stages": [{name, state, seconds, step, max_steps}], "counts": {state: n}}."""
    from services.bench.carry import newest_checkpoint_anywhere
    from services.bench.plan import BenchConfig
    from services.bench.replan import _dry_run
    from services.training.checkpoints import newest_complete_checkpoint, read_checkpoint_state

    work = Path(out_dir) / "work"
    try:
        config = BenchConfig.from_dict(json.loads((work / "plan.json").read_text()))
    except FileNotFoundError:
        raise BenchStatusError(f"{out_dir}: no benchmark here (no work/plan.json); give the --out of `bench paper`") from None
    except (ValueError, KeyError, TypeError) as e:
        raise BenchStatusError(f"{work / 'plan.json'}: not a benchmark plan of this n3dmap ({type(e).__name__}: "
                               f"{e})") from None
    rows = []
    for name in _dry_run(config, work).inputs:
        stage_dir = work / name
        row = {"name": name, "state": "to run", "seconds": None, "step": None, "max_steps": None, "logged": None}
        if (stage_dir / marker_of(name)).exists():
            row["state"] = "finished"
            row["seconds"] = _seconds(stage_dir / "stage.json")
        elif stage_dir.is_dir():
            row["state"] = "under way"
            row["seconds"] = _seconds(stage_dir / PARTIAL)
            if marker_of(name) == TRAIN_MARKER:
                # the checkpoint a resume would use: the newest complete one (a torn newer one is skipped)
                latest = (newest_complete_checkpoint(stage_dir / "checkpoints")
                          or newest_checkpoint_anywhere(stage_dir / "ray_train"))   # a stage on Ray Train
                row["step"] = read_checkpoint_state(latest).step if latest is not None else 0
                rule_name = RULE_OF_PREFIX.get(name.split("/")[-1].split("_")[0])
                rule = getattr(config.rules, rule_name) if rule_name else None
                row["logged"] = last_logged(stage_dir / "metrics.jsonl")
                if rule is not None and rule.kind == "epochs":
                    # its bound is its epochs' steps within [min, max], which the training call logs as its total
                    row["max_steps"] = row["logged"]["total_steps"] if row["logged"] else None
                else:
                    row["max_steps"] = rule.max_steps if rule is not None else None
        rows.append(row)
    counts = {state: sum(r["state"] == state for r in rows) for state in ("finished", "under way", "to run")}
    return {"plan": {"preset": config.preset, "seeds": list(config.seeds)}, "stages": rows, "counts": counts}


def format_status(status: dict, out_dir: str | Path) -> str:
    """The status as lines for a terminal: totals, then per seed what is under way and what runs next."""
    rows, counts, plan = status["stages"], status["counts"], status["plan"]
    done_s = sum(r["seconds"] or 0.0 for r in rows if r["state"] == "finished")
    lines = [f"bench {out_dir}: preset {plan['preset']}, seeds {plan['seeds']}: {counts['finished']} of {len(rows)} "
             f"stages finished ({done_s / 3600:.2f} h of stage time), {counts['under way']} under way, "
             f"{counts['to run']} to run"]
    groups = ["data", *(f"seed{s}" for s in plan["seeds"])]
    for group in groups:
        mine = [r for r in rows if r["name"].split("/")[0] == group]
        finished = sum(r["state"] == "finished" for r in mine)
        line = f"  {group}: {finished} of {len(mine)} finished"
        for r in mine:
            if r["state"] == "under way":
                where = "" if r["step"] is None else f" at step {r['step']}" + (
                    f" (its rule stops by {r['max_steps']})" if r["max_steps"] else "")
                earlier = f", {r['seconds']:.0f} s in stopped attempts" if r["seconds"] else ""
                line += f"; under way: {r['name'].split('/', 1)[-1]}{where}{earlier}{_pace(r['logged'])}"
        upcoming = next((r["name"].split("/", 1)[-1] for r in mine if r["state"] == "to run"), None)
        if upcoming:
            line += f"; next to run: {upcoming}"
        lines.append(line)
    return "\n".join(lines)


def last_logged(metrics_path: Path, tail_bytes: int = 8192) -> dict | None:
    """The training loop's newest progress line of a stage (its metrics.jsonl): {step, total_steps, steps_per_s,
    age_s (seconds since it was written)}, or None (no line yet, or one this reader cannot parse)."""
    try:
        with open(metrics_path, "rb") as f:
            f.seek(max(0, f.seek(0, 2) - tail_bytes))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        try:
            entry = json.loads(line)
            return {"step": int(entry["step"]), "total_steps": int(entry["total_steps"]),
                    "steps_per_s": float(entry.get("steps_per_s") or 0.0),
                    "age_s": max(0.0, time.time() - float(entry["time"]))}
        except (ValueError, KeyError, TypeError):
            continue   # the first line of the tail is cut, or a line of another shape
    return None


def _pace(logged: dict | None) -> str:
    """'; logged step 500 of 800, 0.43 steps/s (~12 min to go at that pace), 1 min ago' ('' without a line)."""
    if not logged:
        return ""
    text = f"; logged step {logged['step']} of {logged['total_steps']}"
    if logged["steps_per_s"] > 0:
        left = (logged["total_steps"] - logged["step"]) / logged["steps_per_s"]
        text += f", {logged['steps_per_s']:.2g} steps/s (~{left / 60:.0f} min to go at that pace)"
    return text + f", {logged['age_s'] / 60:.0f} min ago"


def _seconds(path: Path) -> float | None:
    try:
        return float(json.loads(path.read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
