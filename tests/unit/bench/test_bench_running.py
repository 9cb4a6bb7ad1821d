"""services.bench.running: pid files kept while a block runs, and which of them name live processes (a real
child process stands in for a seed worker; a reaped one, a zombie and a garbled file are not writers)."""

import os
import subprocess
import sys
import time

import pytest

from services.bench.running import RunInProgressError, live_writers, refuse_if_written, running


def test_a_pid_file_is_kept_while_the_block_runs_and_removed_after_it_even_on_an_error(tmp_path):
    path = tmp_path / "work" / "seed0" / "worker.pid"
    with running(path):
        assert int(path.read_text()) == os.getpid()
    assert not path.exists()
    try:
        with running(path):
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        pass
    assert not path.exists()


def test_a_later_process_s_pid_file_is_left_alone(tmp_path):
    path = tmp_path / "bench.pid"
    with running(path):
        path.write_text("1\n")   # a rerun took the file over meanwhile
    assert path.read_text() == "1\n"


def test_live_writers_lists_live_processes_only(tmp_path):
    work = tmp_path / "work"
    (work / "seed1").mkdir(parents=True)
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (work / "seed1" / "worker.pid").write_text(f"{child.pid}\n")
        (work / "garbled.pid").write_text("not a pid")
        with running(work / "bench.pid"):   # this process's own file is not another writer
            assert live_writers(work) == [(work / "seed1" / "worker.pid", child.pid)]
        child.kill()
        child.wait()   # reaped: the pid is gone
        assert live_writers(work) == []
        zombie = subprocess.Popen([sys.executable, "-c", "pass"])
        (work / "seed1" / "worker.pid").write_text(f"{zombie.pid}\n")
        deadline = time.monotonic() + 30
        while open(f"/proc/{zombie.pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z":
            assert time.monotonic() < deadline
            time.sleep(0.01)   # (no poll(): it would reap the child)
        os.kill(zombie.pid, 0)   # exited, not reaped yet: kill(pid, 0) still answers ...
        assert live_writers(work) == []   # ... but it writes nothing any more
        zombie.wait()
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def test_a_second_writer_is_refused_naming_the_first(tmp_path):
    work = tmp_path / "work"
    refuse_if_written(work, "bench paper")   # nothing there yet: fine
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (work / "seed0").mkdir(parents=True)
        (work / "seed0" / "worker.pid").write_text(f"{other.pid}\n")
        with pytest.raises(RunInProgressError, match=rf"being written by pid {other.pid} \(seed0/worker.pid\): bench paper"):
            refuse_if_written(work, "bench paper")
        refuse_if_written(work / "seed1", "seed 1's worker")   # another seed's worker does not stop this one
    finally:
        other.kill()
        other.wait()
    refuse_if_written(work, "bench paper")   # its process gone, its file no longer counts
