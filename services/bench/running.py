"""Which processes are writing a benchmark's work directory now.

Each `bench paper` process keeps OUT/work/bench.pid, and each seed worker OUT/work/seed<S>/worker.pid, while it
runs (`running(path)`: written at the start, removed at the end, also on an exception or a stop by a signal).
`live_writers(work)` lists those whose process is still alive: a second `bench paper` (or seed worker) on the same
work directory is refused (`refuse_if_written`: it would write the same stages), and `bench carry save` never copies
a work directory that a worker is still writing (a worker told to stop finishes its step and saves a checkpoint first,
which takes up to a step's time: ~15 s at small). A pid file left by a process killed outright (SIGKILL) names
a dead pid and is ignored.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from core.errors import N3dmapError

PID_SUFFIX = ".pid"
BENCH_PID = "bench.pid"      # OUT/work/bench.pid: the `bench paper` process
WORKER_PID = "worker.pid"    # OUT/work/seed<S>/worker.pid: a seed worker


@contextmanager
def running(path: str | Path) -> Iterator[Path]:
    """Keep `path` holding this process's pid while the block runs."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f"{os.getpid()}\n")
    os.replace(tmp, path)
    try:
        yield path
    finally:
        try:
            if int(path.read_text()) == os.getpid():   # not a later process's (a rerun started meanwhile)
                path.unlink()
        except (OSError, ValueError):
            pass


class RunInProgressError(N3dmapError):
    """Another live process is writing the work directory."""


def describe(writers: list[tuple[Path, int]], work: Path) -> str:
    return ", ".join(f"pid {pid} ({path.relative_to(work)})" for path, pid in writers)


def refuse_if_written(directory: str | Path, who: str) -> None:
    """RunInProgressError if a live process other than this one keeps a pid file in `directory` (or one level
    down): `who` would write the same stages at the same time."""
    directory = Path(directory)
    writers = live_writers(directory)
    if writers:
        raise RunInProgressError(
            f"{directory} is being written by {describe(writers, directory)}: {who} would write the same stages. "
            "Wait for that run to end, or stop it (SIGTERM or Ctrl-C; its workers save a checkpoint at their "
            "step first, up to ~15 s); if the process named is not a benchmark (a pid reused after a reboot), "
            "delete that pid file")


def live_writers(work: str | Path) -> list[tuple[Path, int]]:
    """(pid file, pid) of every process other than this one that keeps a pid file in `work` (the bench's own
    and its seed workers', one level down) and is alive."""
    work = Path(work)
    found = []
    for path in sorted([*work.glob(f"*{PID_SUFFIX}"), *work.glob(f"*/*{PID_SUFFIX}")]):
        try:
            pid = int(path.read_text())
        except (OSError, ValueError):
            continue
        if pid != os.getpid() and _alive(pid):
            found.append((path, pid))
    return found


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # someone else's process: alive
        return True
    return _not_a_zombie(pid)


def _not_a_zombie(pid: int) -> bool:
    """A child that exited but was not reaped yet still answers kill(pid, 0); /proc tells (Linux; elsewhere
    such a process counts as alive, the safe side for a refusal)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return True
    return fields[0] != "Z"
