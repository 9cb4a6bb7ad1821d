"""A bundle's lineage as text: one line per training run it descends from, newest first.

Why: a bundle's provenance (services.training.job.run_provenance) keeps the provenance of the bundle
it was initialised from under "parents", which keeps its own parents, and so on: a detector trained
through pretrain → egomotion → occupancy → flow nests five levels deep, and printed as JSON that is one
unreadable line. Here each run becomes

    detector(freeze_features=True)  20 steps, seed 0, frozen mapper | data D (train, seed 1000) | run R | git 864e5…
    <- flow(inputs=volume, …)  …
      <- occupancy(…)  …

with the task and its options first, and a parent one step further in than its child. `n3dmap bundle
info --json` still prints the full record. Provenance written by hand or by older code (no "task")
shows its scalar entries instead; malformed entries are shown as such, never raised.
"""

from __future__ import annotations

from pathlib import Path

# Keys run_provenance writes besides the task's own options.
RUN_KEYS = frozenset({"task", "data_manifest", "data_seed", "data_split", "steps", "workers",
                      "batch_size_per_worker", "lr", "seed", "precision", "ema_decay", "init_bundle", "frozen",
                      "git_commit", "run_dir", "run_id", "parents"})
GIT_CHARS = 10


def _value(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def _is_scalar(v) -> bool:
    return isinstance(v, (str, int, float, bool))


def task_label(prov: dict) -> str:
    """`task(option=value, ...)` from the task name and its options (None-valued options left out)."""
    options = ", ".join(f"{k}={_value(v)}" for k, v in prov.items()
                        if k not in RUN_KEYS and v is not None and _is_scalar(v))
    return f"{prov['task']}({options})" if options else str(prov["task"])


def run_details(prov: dict, path: str | None = None) -> str:
    """Steps, seed, precision (unless fp32), weight average (if kept) and frozen modules | data | run dir (or bundle path) | git
    commit, where recorded."""
    training = []
    if prov.get("steps") is not None:
        training.append(f"{prov['steps']} steps")
    if prov.get("seed") is not None:
        training.append(f"seed {prov['seed']}")
    if prov.get("precision") not in (None, "fp32"):
        training.append(str(prov["precision"]))
    if prov.get("ema_decay"):
        training.append(f"weight average {_value(prov['ema_decay'])}")
    if prov.get("frozen"):
        training.append("frozen " + ", ".join(map(str, prov["frozen"])))
    parts = [", ".join(training)] if training else []
    if prov.get("data_manifest"):
        about = [str(prov[k]) for k in ("data_split",) if prov.get(k) is not None]
        if prov.get("data_seed") is not None:
            about.append(f"seed {prov['data_seed']}")
        data = f"data {Path(str(prov['data_manifest'])).parent}"
        parts.append(data + (f" ({', '.join(about)})" if about else ""))
    if prov.get("run_dir"):
        parts.append(f"run {prov['run_dir']}")
    elif path:
        parts.append(f"bundle {path}")
    parts.append(f"git {str(prov['git_commit'])[:GIT_CHARS]}" if prov.get("git_commit") else "git ?")
    return " | ".join(parts)


def describe_run(prov, path: str | None = None) -> str:
    """One line for one run's provenance dict."""
    if not isinstance(prov, dict):
        return f"(malformed provenance: {type(prov).__name__})"
    if "task" not in prov:
        entries = " ".join(f"{k}={_value(v)}" for k, v in sorted(prov.items())
                           if k != "parents" and _is_scalar(v))
        return "(no task recorded)" + (f" {entries}" if entries else "") + (f" | bundle {path}" if path else "")
    return f"{task_label(prov)}  {run_details(prov, path)}"


def lineage_lines(provenance, path: str | None = None, generation: int = 0) -> list[str]:
    """The bundle's own run, then each parent's lineage one step further in (depth first)."""
    prefix = "" if generation == 0 else "  " * (generation - 1) + "<- "
    lines = [prefix + describe_run(provenance, path)]
    parents = provenance.get("parents") if isinstance(provenance, dict) else None
    for parent in parents if isinstance(parents, list) else []:
        if isinstance(parent, dict):
            lines += lineage_lines(parent.get("provenance", {}), parent.get("path"), generation + 1)
        else:
            lines.append("  " * generation + "<- (malformed parent entry)")
    return lines
