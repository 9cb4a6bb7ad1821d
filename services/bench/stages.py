"""Resumable stages: each writes into WORK/<name>/ and is skipped when its output already exists.

A stage is done when its marker file exists (a dataset's manifest.json, a run's bundle/bundle.json, an
evaluation's metrics.json); markers are written last (atomically), so a run cut off mid-stage redoes
that stage only — and a training stage even resumes from its own last checkpoint. Every stage's wall
time is kept in WORK/<name>/stage.json (so a later run that skips it still reports what it cost) and
appended to WORK/stages.jsonl, with the git commit of the code each of its attempts ran (`code`: a run resumed
across commits lists each), so a report names the code behind every number.

Each stage also gets a digest of what determines its output: its own `spec` (task, options, rule, …) and
the digests of the stages it reads (`after`). A digest is a pure function of the plan, so two plans can be
compared stage by stage without running anything (`dry=True`: `run` only records the digest); that is how
`bench paper --rerun-changed` finds the stages a changed plan touches (services.bench.replan).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

from core.errors import N3dmapError
from services.durable import fsync_path


class StageError(N3dmapError):
    """A stage's files say something that cannot be (a marker that does not parse)."""


def write_json(path: Path, value) -> None:
    """Write JSON atomically and durably (temporary name, flushed to disk, then renamed, and the rename flushed):
    a reader never sees half a file, and a power loss after the call cannot leave an empty one behind the name
    (a stage marker that survived empty would say "finished" of a stage with nothing in it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(json.dumps(value, indent=2, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_path(path.parent)


@dataclass
class StageRunner:
    """Runs named stages under `work`, skipping finished ones; `log` gets one line per stage."""

    work: Path
    log: Callable[[str], None] = print
    seconds: dict[str, float] = field(default_factory=dict)   # stage -> wall time (this or an earlier run)
    ran: list[str] = field(default_factory=list)               # stages this invocation actually ran
    dry: bool = False                                          # record digests only; run and create nothing
    digests: dict[str, str] = field(default_factory=dict)      # stage -> digest of its spec and its inputs'
    inputs: dict[str, tuple[str, ...]] = field(default_factory=dict)  # stage -> the stages whose outputs it reads
    specs: dict[str, dict] = field(default_factory=dict)      # stage -> the spec its digest covers (task, options…)
    code: dict[str, list[str]] = field(default_factory=dict)  # stage -> commits its attempts ran (UNRECORDED: unknown)

    def __post_init__(self) -> None:
        self.work = Path(self.work)
        self.commit: str | None = None
        if not self.dry:
            self.work.mkdir(parents=True, exist_ok=True)
            # read once, when the process starts: the code it runs is what it imported then, whatever HEAD says later
            from services.training.job import git_commit
            self.commit = git_commit()

    def dir(self, name: str) -> Path:
        return self.work / name

    def name_of(self, path: Path) -> str:
        """The stage whose directory holds `path` (a stage's output, e.g. its selected bundle)."""
        for parent in (Path(path), *Path(path).parents):
            name = parent.relative_to(self.work).as_posix() if parent.is_relative_to(self.work) else None
            if name in self.digests:
                return name
        raise KeyError(f"{path} is not the output of a stage run so far")

    def record(self, name: str, *, spec: Mapping | None = None, after: Sequence[str] = ()) -> str:
        """Record (and return) stage `name`'s digest without running it (`run` does this first)."""
        # the name too: it carries the seed and what an evaluation computes (two evaluations may read the same)
        self.digests[name] = stage_digest({"stage": name, **(spec or {})}, [self.digests[a] for a in after])
        self.inputs[name] = tuple(after)
        self.specs[name] = dict(spec or {})
        return self.digests[name]

    def run(self, name: str, marker: str, fn: Callable[[Path], None], *, spec: Mapping | None = None,
            after: Sequence[str] = ()) -> Path:
        """Run `fn(stage_dir)` unless `stage_dir/marker` exists; returns stage_dir. spec: JSON-serialisable
        settings that determine the stage's output; after: the stages (run before) whose outputs it reads."""
        self.record(name, spec=spec, after=after)
        stage_dir = self.dir(name)
        if self.dry:
            return stage_dir
        done = stage_dir / marker
        info_path = stage_dir / "stage.json"
        partial_path = stage_dir / PARTIAL
        if done.exists():
            try:
                json.loads(done.read_text())
            except (ValueError, UnicodeDecodeError):
                raise StageError(f"stage {name}: its marker {done} is not readable JSON (cut short by a crash?); "
                                 f"rerun with --redo {name} to run it and what reads it again") from None
            if not info_path.exists() and partial_path.exists():
                # stopped between its marker and its record (a signal in that window): the attempts' time and
                # commits are in PARTIAL, so the record is written from it rather than left a NaN forever
                write_json(info_path, {"stage": name, "seconds": _read_seconds(partial_path),
                                       "code": _read_code(partial_path)})
                partial_path.unlink()
            seconds = _read_seconds(info_path)
            self.seconds[name] = seconds
            self.code[name] = _read_code(info_path)
            self.log(f"[bench] {name}: done earlier ({seconds:.1f} s), skipped")
            self._append(name, seconds, "skipped")
            return stage_dir
        stage_dir.mkdir(parents=True, exist_ok=True)
        # A stage stopped part-way (Ctrl-C, SIGTERM, an error) keeps the time it ran in PARTIAL, and its
        # resume adds it: the report's stage times are whole stages, not their last attempts. (A process
        # killed outright writes nothing, so its attempt goes uncounted.)
        earlier = _read_seconds(partial_path) if partial_path.exists() else 0.0
        code = _read_code(partial_path) if partial_path.exists() else []
        this = self.commit or UNRECORDED   # not a git checkout: unknown, said as such
        if this not in code:
            code = [*code, this]
        # written before the attempt, so that one killed outright (SIGKILL, a lost machine) still names its commit
        write_json(partial_path, {"stage": name, "seconds": earlier, "code": code})
        self.log(f"[bench] {name}: running" + (f" ({earlier:.1f} s in earlier attempts)" if earlier else ""))
        started = time.monotonic()
        try:
            fn(stage_dir)
        except BaseException:
            write_json(partial_path, {"stage": name, "seconds": earlier + time.monotonic() - started, "code": code})
            raise
        seconds = earlier + time.monotonic() - started
        if not done.exists():
            raise RuntimeError(f"stage {name} finished without writing {done}")
        write_json(info_path, {"stage": name, "seconds": seconds, "code": code})
        partial_path.unlink(missing_ok=True)
        self.seconds[name] = seconds
        self.code[name] = code
        self.ran.append(name)
        self.log(f"[bench] {name}: {seconds:.1f} s")
        self._append(name, seconds, "ran")
        return stage_dir

    def _append(self, name: str, seconds: float, status: str) -> None:
        with open(self.work / JOURNAL, "a") as f:
            f.write(json.dumps({"stage": name, "seconds": round(seconds, 3), "status": status,
                                "time": time.strftime("%Y-%m-%dT%H:%M:%S"), "code": self.commit}) + "\n")


# one line per stage and invocation: {stage, seconds, status ("ran"/"skipped"), time, code (this process's commit)}
JOURNAL = "stages.jsonl"
PARTIAL = "stage.partial.json"   # in a stage's dir: {stage, seconds, code} its stopped attempts ran so far


def journal_size(work: Path) -> int:
    """Bytes of WORK/stages.jsonl now (0 when absent): where the lines of what runs next begin."""
    path = Path(work) / JOURNAL
    return path.stat().st_size if path.exists() else 0


def stages_ran_since(work: Path, offset: int) -> list[str]:
    """The stages journaled as "ran" after byte `offset` of WORK/stages.jsonl, in journal order: what seed
    worker processes ran for this invocation (each appends to the same journal)."""
    path = Path(work) / JOURNAL
    if not path.exists():
        return []
    with open(path, "rb") as f:
        f.seek(offset)
        lines = f.read().decode().splitlines()
    ran = []
    for line in lines:
        try:
            entry = json.loads(line)
        except ValueError:
            continue   # a line cut off by a killed worker: its stage has no completion marker and reruns anyway
        if entry.get("status") == "ran":
            ran.append(entry["stage"])
    return ran


def stage_digest(spec: Mapping, inputs: Sequence[str]) -> str:
    """sha256 of a stage's spec and its inputs' digests (canonical JSON: key order does not matter)."""
    text = json.dumps({"spec": spec, "inputs": list(inputs)}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


UNRECORDED = "?"   # in a stage's `code`: attempts whose commit was not recorded (they ran before it was)


def _read_code(path: Path) -> list[str]:
    """The commits a stage.json / PARTIAL records; [UNRECORDED] when it has none (written before they were kept)."""
    try:
        code = json.loads(path.read_text()).get("code")
    except (OSError, ValueError, AttributeError):
        return [UNRECORDED]
    return [str(c) for c in code] if isinstance(code, list) else [UNRECORDED]


def _read_seconds(path: Path) -> float:
    try:
        return float(json.loads(path.read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return float("nan")
