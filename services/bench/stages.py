"""Resumable stages: each writes into WORK/<name>/ and is skipped when its output already exists.

A stage is done when its marker file exists (a dataset's manifest.json, a run's bundle/bundle.json, an
evaluation's metrics.json); markers are written last (atomically), so a run cut off mid-stage redoes
that stage only — and a training stage even resumes from its own last checkpoint. Every stage's wall
time is kept in WORK/<name>/stage.json (so a later run that skips it still reports what it cost) and
appended to WORK/stages.jsonl.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable


def write_json(path: Path, value) -> None:
    """Write JSON atomically (temporary name, then rename): a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)


@dataclass
class StageRunner:
    """Runs named stages under `work`, skipping finished ones; `log` gets one line per stage."""

    work: Path
    log: Callable[[str], None] = print
    seconds: dict[str, float] = field(default_factory=dict)   # stage -> wall time (this or an earlier run)
    ran: list[str] = field(default_factory=list)               # stages this invocation actually ran

    def __post_init__(self) -> None:
        self.work = Path(self.work)
        self.work.mkdir(parents=True, exist_ok=True)

    def dir(self, name: str) -> Path:
        return self.work / name

    def run(self, name: str, marker: str, fn: Callable[[Path], None]) -> Path:
        """Run `fn(stage_dir)` unless `stage_dir/marker` exists; returns stage_dir."""
        stage_dir = self.dir(name)
        done = stage_dir / marker
        info_path = stage_dir / "stage.json"
        if done.exists():
            seconds = _read_seconds(info_path)
            self.seconds[name] = seconds
            self.log(f"[bench] {name}: done earlier ({seconds:.1f} s), skipped")
            self._append(name, seconds, "skipped")
            return stage_dir
        stage_dir.mkdir(parents=True, exist_ok=True)
        self.log(f"[bench] {name}: running")
        started = time.monotonic()
        fn(stage_dir)
        seconds = time.monotonic() - started
        if not done.exists():
            raise RuntimeError(f"stage {name} finished without writing {done}")
        write_json(info_path, {"stage": name, "seconds": seconds})
        self.seconds[name] = seconds
        self.ran.append(name)
        self.log(f"[bench] {name}: {seconds:.1f} s")
        self._append(name, seconds, "ran")
        return stage_dir

    def _append(self, name: str, seconds: float, status: str) -> None:
        with open(self.work / "stages.jsonl", "a") as f:
            f.write(json.dumps({"stage": name, "seconds": round(seconds, 3), "status": status,
                                "time": time.strftime("%Y-%m-%dT%H:%M:%S")}) + "\n")


def _read_seconds(path: Path) -> float:
    try:
        return float(json.loads(path.read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return float("nan")
