"""`bench paper --rerun-changed`: continue a benchmark under a changed plan, redoing only what it touches.

Every stage has a digest of what determines its output — its own settings and the digests of the stages
it reads (services.bench.stages) — and a digest is a pure function of the plan. So the stages a change
touches are found by walking the old and the new plan without running anything (`StageRunner(dry=True)`)
and comparing digests: a changed flow option touches the flow stages and the evaluations that read them,
not the pretrainings or the detectors. Those stages' directories are deleted, and so are those of stages
the new plan no longer has (a label budget dropped, say); the rerun then redoes the touched ones and skips
the rest as usual.

Code changes are not in the digests: after changing code, name the stages it affects with `bench paper
--redo PATTERN` (`forget_matching`): the stages whose names match, and every stage that reads their output
(directly or further down), are deleted and redone.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import replace
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Callable

from services.bench.plan import BenchConfig, BenchConfigError
from services.bench.stages import StageRunner


def _dry_run(config: BenchConfig, work: Path) -> StageRunner:
    """Every stage `config` runs, recorded (digests and inputs) without running or writing anything."""
    from services.bench.paper import _data_stages
    from services.bench.seed_stages import seed_stages

    stages = StageRunner(work, log=lambda _: None, dry=True)
    data = _data_stages(stages, config)
    for seed in config.seeds:
        seed_stages(stages, config, seed, data, [], [], "cpu")
    return stages


def stage_digests(config: BenchConfig, work: Path) -> dict[str, str]:
    """{stage name: digest} of every stage `config` runs (nothing is run or written)."""
    return _dry_run(config, work).digests


def matching_and_downstream(config: BenchConfig, work: Path, patterns: Sequence[str]) -> list[str]:
    """The stages of `config` whose names match any of the shell-style `patterns` (fnmatch: `*` also
    matches `/`, e.g. "seed*/egomotion", "seed*/eval/occupancy/*"), and every stage that reads one of them,
    directly or through others; in the plan's order. A pattern that matches no stage is an error."""
    # seeds with output on disk too: a seed left out of this run must not keep a stale stage for a later one
    seeds = tuple(sorted(set(config.seeds) | _seeds_on_disk(Path(work))))
    stages = _dry_run(replace(config, seeds=seeds), work)
    names = list(stages.inputs)
    unmatched = [p for p in patterns if not any(fnmatchcase(n, p) for n in names)]
    if unmatched:
        raise BenchConfigError(f"--redo {unmatched[0]!r} matches no stage of this plan (stage names look like "
                               f"{', '.join(repr(n) for n in names[-3:])}; the report's stage table lists them all)")
    chosen = {n for n in names if any(fnmatchcase(n, p) for p in patterns)}
    for name in names:   # the plan records a stage after every stage it reads, so one pass closes the set
        if chosen.intersection(stages.inputs[name]):
            chosen.add(name)
    return [n for n in names if n in chosen]


def forget_matching(config: BenchConfig, work: Path, patterns: Sequence[str], log: Callable[[str], None]) -> list[str]:
    """Delete the output of the stages `matching_and_downstream` names; returns those that had output."""
    return _forget(matching_and_downstream(config, work, patterns), work, f"--redo {' '.join(patterns)}", log)


def _forget(names: Sequence[str], work: Path, why: str, log: Callable[[str], None]) -> list[str]:
    """Delete the directories of the stages `names` under `work`; returns those that existed."""
    removed = []
    for name in names:
        stage_dir = Path(work) / name
        if stage_dir.exists():
            shutil.rmtree(stage_dir)
            removed.append(name)
    log(f"[bench] {why}: {len(removed)} finished or started stage(s) redone"
        + (f": {', '.join(removed)}" if removed else ""))
    return removed


def changed_stages(earlier: BenchConfig, current: BenchConfig, work: Path) -> list[str]:
    """Stages whose digest differs between the plans, or that only `earlier` has, over every seed of either
    plan and every seed with a directory under `work`: a seed left out of this run but rerun later with the
    same plan must not keep the old plan's stages (plans are compared without their seeds)."""
    seeds = tuple(sorted(set(earlier.seeds) | set(current.seeds) | _seeds_on_disk(Path(work))))
    old = stage_digests(replace(earlier, seeds=seeds), work)
    new = stage_digests(replace(current, seeds=seeds), work)
    return [name for name, digest in new.items() if old.get(name) != digest] + [name for name in old if name not in new]


def _seeds_on_disk(work: Path) -> set[int]:
    return {int(d.name[len("seed"):]) for d in work.glob("seed*") if d.is_dir() and d.name[len("seed"):].isdigit()}


def forget_changed(earlier: BenchConfig, current: BenchConfig, work: Path, log: Callable[[str], None]) -> list[str]:
    """Delete the output of every stage the change from `earlier` to `current` touches or drops; returns their
    names (those that had output)."""
    return _forget(changed_stages(earlier, current, work), work, "plan changed", log)
