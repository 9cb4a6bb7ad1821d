"""`bench paper --rerun-changed`: continue a benchmark under a changed plan, redoing only what it touches.

Every stage has a digest of what determines its output — its own settings and the digests of the stages
it reads (services.bench.stages) — and a digest is a pure function of the plan. So the stages a change
touches are found by walking the old and the new plan without running anything (`StageRunner(dry=True)`)
and comparing digests: a changed flow option touches the flow stages and the evaluations that read them,
not the pretrainings or the detectors. Those stages' directories are deleted, and so are those of stages
the new plan no longer has (a label budget dropped, say); the rerun then redoes the touched ones and skips
the rest as usual.

Code changes are not in the digests: after changing code, delete the stages it affects by hand.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path
from typing import Callable

from services.bench.plan import BenchConfig
from services.bench.stages import StageRunner


def stage_digests(config: BenchConfig, work: Path) -> dict[str, str]:
    """{stage name: digest} of every stage `config` runs (nothing is run or written)."""
    from services.bench.paper import _data_stages, _seed_stages

    stages = StageRunner(work, log=lambda _: None, dry=True)
    data = _data_stages(stages, config)
    for seed in config.seeds:
        _seed_stages(stages, config, seed, data, [], [], "cpu")
    return stages.digests


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
    removed = []
    for name in changed_stages(earlier, current, work):
        stage_dir = Path(work) / name
        if stage_dir.exists():
            shutil.rmtree(stage_dir)
            removed.append(name)
    log(f"[bench] plan changed: {len(removed)} finished or started stage(s) redone"
        + (f": {', '.join(removed)}" if removed else ""))
    return removed
