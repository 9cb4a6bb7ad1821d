"""Carry a `bench paper` run from one machine to another: the part of its work that cannot be remade, in a
folder that git can hold.

The small preset's benchmark trains for about fifteen hours of a 2-core machine, over several sessions, and
a machine can be replaced between two of them (three regenerations of the small report were lost that way,
their work directories with them). `save_carry(OUT, CARRY)` writes into CARRY what a rerun needs and cannot
regenerate; on another machine `restore_carry(CARRY, OUT)` rebuilds OUT/work from it, after which the same
`n3dmap bench paper --out OUT ...` command continues where the saved run stopped.

What is carried: OUT/work/plan.json, OUT/work/stages.jsonl and every file under OUT/work/seed<s>/, except
- the datasets (OUT/work/data/*; only their stage.json, the time they took, is carried): the restore
  regenerates them from the plan (the generator is deterministic: the same code and torch write the same
  bytes) and checks each shard's sha256 against the carried manifests, so a resumed stage never trains on
  other bytes than its first part did;
- the label subsets (RUN_DIR/labelled_data/): copies of training records, remade by the stage that reads them;
- a training run's exported RUN_DIR/bundle/: remade by its next export (later stages read RUN_DIR/selected/);
- checkpoints: none of a finished training stage (its output is RUN_DIR/selected/), and of a stage under way
  only the one its rerun resumes from (the loop's newest `checkpoint_<step>`; older ones are never read, and a
  `.staging_*` folder is a checkpoint a kill cut off before it was committed);
- temporaries (*.tmp, selected.old) and the pid files of the processes writing the run (services.bench.running).

CARRY/carry.json lists every carried file with its size and sha256 (the restore checks each) and the data
manifests. A run is saved only while nothing writes to it: `save_carry` refuses while the `bench paper` process
or a seed worker of it is alive (services.bench.running); stop it first (SIGTERM or Ctrl-C: its stages save a
checkpoint at the step they are in).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Callable, Iterator

from core.data.shards import sha256_file
from core.errors import N3dmapError
from services.bench.running import PID_SUFFIX, describe, live_writers
from services.bench.stages import write_json

CARRY_FORMAT = "n3dmap-bench-carry"
CARRY_VERSION = 1
CARRY_MANIFEST = "carry.json"
DATA_STAGE_ROOT = "data"
TOP_FILES = ("plan.json", "stages.jsonl")
# Directories of a training run that are never carried (see the module docstring).
REMADE_DIRS = ("labelled_data", "bundle")
CHECKPOINTS = "checkpoints"   # TrainJobConfig.local_checkpoint_root: the in-process loop's
RAY_STORAGE = "ray_train"     # TrainJobConfig.ray_storage_name: Ray Train's (its own layout; not carried)
# What marks a directory as a training run's (a stage's RUN_DIR), from the moment the stage starts.
RUN_DIR_NAMES = frozenset({"metrics.jsonl", "stopping.json", "stopping.partial.json", "selected", CHECKPOINTS,
                           RAY_STORAGE, *REMADE_DIRS})
TEMPORARY_SUFFIXES = (".tmp", ".old")
TRAINING_MARKER = "stopping.json"                 # services.bench.stopping.MARKER: the stage is finished
STAGE_INFO = "stage.json"                         # a finished stage's wall time (services.bench.stages)


class CarryError(N3dmapError):
    """A carry folder or a benchmark work directory cannot be saved or restored as asked."""


def save_carry(out_dir: str | Path, carry_dir: str | Path, *, log: Callable[[str], None] = print) -> dict:
    """Write what OUT/work cannot remake into CARRY_DIR (replacing an earlier carry there); returns carry.json."""
    work = Path(out_dir).resolve() / "work"
    carry = Path(carry_dir).resolve()   # resolved: `--to .` has no name to put the temporary folder beside
    if not (work / "plan.json").is_file():
        raise CarryError(f"{out_dir}: no benchmark here (no work/plan.json); give the --out of `bench paper`")
    _refuse_unsafe_target(work.parent, carry, carry_dir)
    _refuse_if_written(work)
    data = {}
    for manifest_path in sorted((work / DATA_STAGE_ROOT).glob("*/manifest.json")):
        manifest = json.loads(manifest_path.read_text())
        data[manifest_path.parent.name] = manifest
    files = sorted(carried_files(work))
    tmp = carry.with_name(carry.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    listing = {}
    for rel in files:
        target = tmp / "work" / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(work / rel, target)
        listing[rel] = {"bytes": target.stat().st_size, "sha256": sha256_file(target)}
    manifest = {"format": CARRY_FORMAT, "version": CARRY_VERSION, "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "progress": progress(work, listing), "data": data, "files": listing}
    _refuse_if_written(work, tmp)   # a run started while we copied: the copy may be half old, half new
    write_json(tmp / CARRY_MANIFEST, manifest)
    if carry.is_dir():   # hand-written files beside the carry (what run it is, how to continue it) stay
        for kept in carry.iterdir():
            if kept.is_file() and kept.name != CARRY_MANIFEST:
                shutil.copy2(kept, tmp / kept.name)
    old = carry.with_name(carry.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if carry.exists():
        os.replace(carry, old)
    os.replace(tmp, carry)
    shutil.rmtree(old, ignore_errors=True)
    total = sum(f["bytes"] for f in listing.values())
    done = manifest["progress"]
    log(f"[carry] saved {len(listing)} files ({total / 1e6:.1f} MB) of {work} to {carry}: "
        f"{len(done['finished'])} stages finished, {len(done['under_way'])} under way"
        + "".join(f"\n[carry]   under way: {stage} at step {step}" for stage, step in done["under_way"].items()))
    return manifest


def _refuse_unsafe_target(out: Path, carry: Path, given: str | Path) -> None:
    """CarryError unless `carry` (resolved) may be replaced by a carry of the benchmark in `out` (resolved): it must
    lie outside the benchmark (a carry replaces its folder whole: inside `--out` it would delete the run's datasets
    and stages, above it the run itself), and a save may lose nothing there: its top-level files are kept (notes
    beside the carry), its `work/` is replaced only when carry.json says it is an earlier carry's, and any other
    folder in it refuses the save."""
    if carry == out or carry.is_relative_to(out) or out.is_relative_to(carry):
        raise CarryError(f"--to {given}: it must lie outside the benchmark's --out {out} (the carry replaces its "
                         "folder whole, which would delete the run's own files)")
    if carry.exists() and not carry.is_dir():
        raise CarryError(f"--to {given}: a file is there, not a folder")
    if carry.is_dir():
        earlier = (carry / CARRY_MANIFEST).is_file()
        lost = sorted(p.name for p in carry.iterdir() if p.is_dir() and not (p.name == "work" and earlier))
        if lost:
            raise CarryError(f"--to {given}: holds folder(s) {lost} that a save would delete (it is not an earlier "
                             f"carry{'' if earlier else f', no {CARRY_MANIFEST}'}); give a new or empty folder")


def progress(work: Path, listing: dict) -> dict:
    """{"finished": [stage, …], "under_way": {stage: checkpoint step or None}} of the seeds' stages in a carry's
    file list: a stage is finished when its marker (a training run's stopping.json, an evaluation's
    metrics.json) is carried, under way when only its stage.partial.json or its run files are."""
    finished, under_way = [], {}
    for rel in listing:
        parts = rel.split("/")
        if parts[0] in TOP_FILES or parts[0] == DATA_STAGE_ROOT:
            continue
        name = parts[-1]
        if name == TRAINING_MARKER or (name == "metrics.json" and "/eval/" in f"/{rel}"):
            finished.append("/".join(parts[:-1]))
    for rel in listing:
        parts = rel.split("/")
        if CHECKPOINTS in parts and parts[-1] == "state.json":
            stage = "/".join(parts[:parts.index(CHECKPOINTS)])
            under_way[stage] = int(json.loads((work / rel).read_text())["step"])
        elif parts[-1] in ("stage.partial.json", "stopping.partial.json"):
            stage = "/".join(parts[:-1])
            if stage not in finished:
                under_way.setdefault(stage, None)
    return {"finished": sorted(finished), "under_way": dict(sorted(under_way.items()))}


def _refuse_if_written(work: Path, partial_copy: Path | None = None) -> None:
    live = live_writers(work)
    if live:
        if partial_copy is not None:
            shutil.rmtree(partial_copy, ignore_errors=True)
        raise CarryError(f"{work} is still being written by {describe(live, work)}: stop `bench paper` first "
                         "(SIGTERM or Ctrl-C) and wait for its workers to save their checkpoints and exit; if the "
                         "process named is not a benchmark (a pid reused after a reboot), delete that pid file")


def carried_files(work: Path) -> Iterator[str]:
    """Paths (relative to `work`, POSIX) of the files a carry holds (module docstring)."""
    for name in TOP_FILES:
        if (work / name).is_file():
            yield name
    for stage_json in sorted((work / DATA_STAGE_ROOT).glob(f"*/{STAGE_INFO}")):
        yield stage_json.relative_to(work).as_posix()   # the data stages' times, for the report
    for seed_dir in sorted(p for p in work.iterdir() if p.is_dir() and p.name != DATA_STAGE_ROOT):
        yield from _walk(work, seed_dir)


def _walk(work: Path, directory: Path) -> Iterator[str]:
    names = set(os.listdir(directory))
    run_dir = bool(names & RUN_DIR_NAMES)
    finished = TRAINING_MARKER in names
    for name in sorted(names):
        path = directory / name
        if name.endswith(TEMPORARY_SUFFIXES) or name.endswith(PID_SUFFIX):
            continue
        if path.is_dir():
            if run_dir and name in REMADE_DIRS:
                continue
            if run_dir and name == RAY_STORAGE:
                if not finished and newest_checkpoint_anywhere(path) is not None:
                    raise CarryError(f"{directory} is a stage under way on Ray Train (bench paper --workers N), "
                                     "whose checkpoints are not carried; carry it once that stage has finished, "
                                     "or run the benchmark in-process (--workers 0)")
                continue
            if run_dir and name == CHECKPOINTS:
                newest = None if finished else _resumed_checkpoint(path)
                if newest is not None:
                    yield from _walk(work, newest)
                continue
            yield from _walk(work, path)
        elif path.is_file():
            yield path.relative_to(work).as_posix()


def _resumed_checkpoint(root: Path) -> Path | None:
    """The checkpoint the in-process loop resumes from: its own store's newest complete `checkpoint_<step>`
    (never a `.staging_*` folder that a kill left behind, whatever step it holds, nor a newer one cut short,
    which the loop would skip: carrying that one alone left no checkpoint to resume from)."""
    from services.training.checkpoints import newest_complete_checkpoint

    return newest_complete_checkpoint(root)


def newest_checkpoint_anywhere(root: Path) -> Path | None:
    """Any checkpoint (a folder with a readable state.json) of the highest step under `root`, at any depth (Ray
    Train nests its checkpoints one level further than the in-process loop): is a Ray stage under way?"""
    best, best_step = None, -1
    for state in root.rglob("state.json"):
        try:
            step = int(json.loads(state.read_text())["step"])
        except (OSError, ValueError, KeyError, TypeError):
            continue   # a checkpoint cut off while it was written: never the one a rerun resumes from
        if step > best_step:
            best, best_step = state.parent, step
    return best


def restore_carry(carry_dir: str | Path, out_dir: str | Path, *, log: Callable[[str], None] = print) -> dict:
    """Rebuild OUT/work from CARRY_DIR (OUT/work must not exist yet), regenerating the datasets and checking
    them and every carried file against carry.json; returns carry.json. Everything is built in a folder beside
    OUT/work and moved into place only once it all checked out: a refused or interrupted restore leaves no
    work directory a `bench paper` rerun could take for a benchmark."""
    from services.bench.paper import _data_stages
    from services.bench.plan import BenchConfig
    from services.bench.stages import StageRunner

    carry = Path(carry_dir)
    work = Path(out_dir) / "work"
    manifest = read_carry_manifest(carry)
    if work.exists() and any(work.iterdir()):
        raise CarryError(f"{work} already holds a benchmark; restore into a new --out (or delete it first)")
    for rel, info in manifest["files"].items():
        source = carry / "work" / rel
        if not source.is_file():
            raise CarryError(f"{carry}: carried file work/{rel} is missing")
        if source.stat().st_size != info["bytes"] or sha256_file(source) != info["sha256"]:
            raise CarryError(f"{carry}: carried file work/{rel} does not match its sha256 in {CARRY_MANIFEST} "
                             "(changed or truncated since it was saved)")
    try:   # checked before anything is written (its sha256 matched: the file is the one saved)
        config = BenchConfig.from_dict(json.loads((carry / "work" / "plan.json").read_text()))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CarryError(f"{carry}: work/plan.json is not a benchmark plan of this n3dmap "
                         f"({type(e).__name__}: {e})") from None
    tmp = work.with_name(work.name + ".restoring")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        data_times = []
        for rel in manifest["files"]:
            if rel.startswith(f"{DATA_STAGE_ROOT}/"):
                data_times.append(rel)   # copied over the regenerated stages' own times below
                continue
            target = tmp / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(carry / "work" / rel, target)
        _data_stages(StageRunner(tmp, log), config)
        _check_regenerated_data(manifest["data"], tmp)
        for rel in data_times:
            shutil.copyfile(carry / "work" / rel, tmp / rel)
        work.parent.mkdir(parents=True, exist_ok=True)
        if work.exists():
            work.rmdir()   # empty (checked above)
        os.replace(tmp, work)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log(f"[carry] restored {len(manifest['files'])} files from {carry} into {work}; datasets regenerated and "
        "checked: rerun the same `bench paper` command to continue")
    return manifest


def _check_regenerated_data(carried_data: dict, work: Path) -> None:
    """CarryError unless every regenerated dataset under `work` has the carried manifests' shards, byte for byte."""
    for split, carried in carried_data.items():
        remade = json.loads((work / DATA_STAGE_ROOT / split / "manifest.json").read_text())
        if len(carried["shards"]) != len(remade["shards"]):
            raise CarryError(f"the regenerated dataset {DATA_STAGE_ROOT}/{split} has {len(remade['shards'])} shards, "
                             f"the carried run's had {len(carried['shards'])}")
        for want, have in zip(carried["shards"], remade["shards"]):
            if (want["filename"], want["sha256"]) != (have["filename"], have["sha256"]):
                raise CarryError(
                    f"the regenerated dataset {DATA_STAGE_ROOT}/{split} differs from the carried run's in "
                    f"{want['filename']} (sha256 {have['sha256'][:12]}… here, {want['sha256'][:12]}… then): its "
                    "stages were trained on other bytes (another n3dmap or torch); continue it with the code it "
                    "was saved from, or start the benchmark again")


def read_carry_manifest(carry: Path) -> dict:
    path = Path(carry) / CARRY_MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise CarryError(f"{carry}: no {CARRY_MANIFEST} (not a folder written by `bench carry save`)") from None
    except ValueError as e:
        raise CarryError(f"{path}: not JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != CARRY_FORMAT:
        raise CarryError(f"{path}: not a bench carry manifest (format {manifest.get('format')!r})"
                         if isinstance(manifest, dict) else f"{path}: not a bench carry manifest")
    if manifest.get("version") != CARRY_VERSION:
        raise CarryError(f"{path}: carry version {manifest.get('version')!r}; this n3dmap reads {CARRY_VERSION}")
    for key in ("data", "files"):
        if not isinstance(manifest.get(key), dict):
            raise CarryError(f"{path}: field {key!r} missing or not an object")
    if "plan.json" not in manifest["files"]:
        raise CarryError(f"{path}: files lacks plan.json (the benchmark's plan, which the restore regenerates the "
                         "datasets from)")
    for rel, info in manifest["files"].items():
        if Path(rel).is_absolute() or ".." in Path(rel).parts or "\\" in rel:
            raise CarryError(f"{path}: file path {rel!r} leaves the work directory")
        if not (isinstance(info, dict) and isinstance(info.get("bytes"), int) and isinstance(info.get("sha256"), str)):
            raise CarryError(f"{path}: files[{rel!r}] needs integer 'bytes' and string 'sha256'")
    for split, data in manifest["data"].items():
        shards = data.get("shards") if isinstance(data, dict) else None
        if not isinstance(shards, list) or not all(isinstance(s, dict) and {"filename", "sha256"} <= set(s)
                                                  for s in shards):
            raise CarryError(f"{path}: data[{split!r}] needs a 'shards' list of {{filename, sha256}}")
    return manifest
