"""A seed worker stops when the `bench paper` process that started it is gone (services.bench.seed_worker.
exit_with_parent), so a parent killed without its clean-up never leaves a worker training beside the rerun's.
Real processes: a parent starts a child that watches it, the parent exits without stopping the child."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]

CHILD = ("import time; from services.bench.seed_worker import exit_with_parent; exit_with_parent(poll_s=0.05); "
         "print('watching', flush=True); time.sleep(60)")
# The parent starts the child, waits until it watches, prints its pid and exits at once, leaving it running.
PARENT = ("import subprocess, sys; child = subprocess.Popen([sys.executable, '-c', sys.argv[1]], "
          "stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True); child.stdout.readline(); print(child.pid, flush=True)")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_worker_whose_parent_is_gone_stops():
    parent = subprocess.run([sys.executable, "-c", PARENT, CHILD], capture_output=True, text=True, timeout=60,
                            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert parent.returncode == 0, parent.stderr
    child = int(parent.stdout.strip())
    try:
        deadline = time.monotonic() + 10
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child), "the worker outlived its parent by 10 s"
    finally:
        if _alive(child):
            os.kill(child, 9)


def test_a_worker_told_its_parent_stops_even_if_that_parent_was_gone_at_start_up():
    """The parent passes its pid: a worker that starts after its parent died (adopted already) still stops."""
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          timeout=30).stdout.strip()
    child = subprocess.Popen([sys.executable, "-c", CHILD.replace("exit_with_parent(poll_s=0.05)",
                                                                   f"exit_with_parent({int(gone)}, poll_s=0.05)")],
                             stdout=subprocess.PIPE, text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        child.wait(timeout=10)
        assert child.returncode == -15  # SIGTERM
    finally:
        if child.poll() is None:
            child.kill()
            child.wait(timeout=10)


def test_a_worker_with_its_parent_keeps_running():
    child = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True, cwd=REPO,
                             env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert child.stdout.readline().strip() == "watching"
        time.sleep(0.5)  # ten polls
        assert child.poll() is None
    finally:
        child.kill()
        child.wait(timeout=10)


def test_a_worker_stopped_by_a_signal_says_so_and_exits_130(monkeypatch, capsys):
    """A training stage stopped by SIGINT / SIGTERM raises TrainingInterrupted (its checkpoint saved): the
    worker reports it in one line and exits 130, which the parent reports as a stopped, resumable seed."""
    import services.bench.paper as paper
    from services.bench import seed_worker
    from services.training.loop import TrainingInterrupted

    def stopped(out, seed, log):
        raise TrainingInterrupted("stopped by SIGTERM after step 37 of 100; its checkpoint is saved in RUN: rerun "
                                  "the same command to resume there")

    monkeypatch.setattr(paper, "run_one_seed", stopped)
    monkeypatch.setattr(seed_worker, "exit_with_parent", lambda parent=None: None)
    import signal

    before = signal.getsignal(signal.SIGTERM)  # main() turns SIGTERM into KeyboardInterrupt for the worker
    try:
        assert seed_worker.main(["--out", "unused", "--seed", "4", "--threads", "1"]) == seed_worker.STOPPED_EXIT == 130
    finally:
        signal.signal(signal.SIGTERM, before)
    out = capsys.readouterr().out.splitlines()
    assert out[-1] == ("[bench] seed 4: stopped (stopped by SIGTERM after step 37 of 100; its checkpoint is saved "
                       "in RUN: rerun the same command to resume there); a rerun resumes it")
