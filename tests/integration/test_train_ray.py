"""Real 2-worker Ray Train runs of the pretrain task on an embedded local Ray (tiny preset).

One run loses its rank-0 worker process mid-run (os._exit after the step-2 checkpoint, first attempt
only) and must be retried from that checkpoint and finish; rerunning the same command with more steps
must resume at the saved step rather than start over.
"""

import pytest

from services.training.checkpoints import read_checkpoint_state
from services.training.config import TrainJobConfig
from services.training.progress import read_metrics

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.fixture(scope="module")
def killed_run(tiny_train_data, tmp_path_factory):
    """A 2-worker regression run whose rank-0 worker dies at step 3 (checkpoints at 2 and 4)."""
    from services.training.job import run_training

    run_dir = tmp_path_factory.mktemp("ray_run")
    config = TrainJobConfig(task="pretrain", task_options={"objective": "regression"},
                            data_dir=str(tiny_train_data), run_dir=str(run_dir), preset="tiny",
                            workers=2, steps=4, batch_size=1, checkpoint_every=2, log_every=1,
                            max_failures=1, fault_at_step=3, object_store_mb=100, device="cpu")
    return config, run_training(config)


def test_killed_worker_is_retried_from_the_last_checkpoint(killed_run):
    config, summary = killed_run
    assert config.fault_marker_path.exists()  # the worker really died once
    assert summary.outcome.status == "finished" and summary.outcome.step == 4
    assert summary.outcome.start_step == 2  # the retry restored the step-2 checkpoint
    records = read_metrics(config.metrics_path)
    first_attempt = [r["step"] for r in records if r["start_step"] == 0]
    retry = [r["step"] for r in records if r["start_step"] == 2]
    assert first_attempt == [1, 2, 3] and retry == [3, 4]
    assert read_checkpoint_state(summary.checkpoint_dir).step == 4
    assert summary.checkpoint_dir.parent == config.run_path / "ray_train"
    assert (config.bundle_path / "bundle.json").is_file()


def test_rerun_resumes_at_the_saved_step(killed_run, capsys):
    from core.bundle import load_bundle
    from services.cli.main import main

    config, _ = killed_run
    rc = main(["train", "pretrain", "--objective", "regression", "--data", config.data_dir,
               "--run-dir", config.run_dir, "--workers", "2", "--steps", "6", "--batch-size", "1",
               "--checkpoint-every", "2", "--log-every", "1", "--object-store-mb", "100", "--device", "cpu"])
    out = capsys.readouterr().out
    assert rc == 0, out
    # The driver prints the workers' progress (read back from metrics.jsonl), not Ray's logs.
    assert "workers (re)started from the checkpoint at step 4" in out
    assert "step 6/6 (100%)" in out
    records = [r for r in read_metrics(config.metrics_path) if r["start_step"] == 4]
    assert [r["step"] for r in records] == [5, 6]
    assert load_bundle(config.bundle_path).meta["provenance"]["steps"] == 6


def test_a_bad_record_ends_a_two_worker_run_naming_it(tiny_train_data, tmp_path):
    """One undecodable record (the shard's size unchanged, so only decoding finds it) reaches one rank only: the
    run ends at once with one line naming the record, exit 2. Before, that rank returned an error while the other
    waited in its next collective for gloo's 30-minute timeout (run here in a subprocess with a deadline, so a
    hang fails the test instead of the suite)."""
    import json
    import os
    import shutil
    import signal
    import subprocess
    import sys
    import tarfile
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    data = tmp_path / "data"
    shutil.copytree(tiny_train_data, data)
    shard_entry = json.loads((data / "manifest.json").read_text())["shards"][-1]
    shard, key = data / shard_entry["filename"], shard_entry["keys"][0]
    with tarfile.open(shard) as tar:
        member = next(m for m in tar.getmembers() if m.name.startswith(key))
    with open(shard, "r+b") as f:
        f.seek(member.offset_data)
        f.write(b"\0" * 64)   # the npz's zip header gone, every byte count as before
    command = [sys.executable, "-m", "services.cli.main", "train", "pretrain", "--objective", "regression",
               "--data", str(data), "--run-dir", str(tmp_path / "run"), "--workers", "2", "--steps", "40",
               "--batch-size", "1", "--max-failures", "0", "--object-store-mb", "100", "--device", "cpu"]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(command, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)   # its own process group: the embedded Ray goes with it
    try:
        out, err = proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("the run with a bad record did not end within 300 s")
    assert proc.returncode == 2, out[-2000:] + err[-2000:]
    last = err.strip().splitlines()[-1]
    assert "training failed" in last and f"{shard_entry['filename']} record {key}" in last, err[-2000:]


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_ends_a_two_worker_run_as_an_interruption(tiny_train_data, tmp_path, sig):
    """SIGINT (Ctrl-C) or SIGTERM (`kill`, `ray job stop`) to `n3dmap train --workers 2` once its first checkpoint
    is written: the run ends (exit 130, the one line naming its last checkpoint, where a rerun resumes:
    test_rerun_resumes_at_the_saved_step), not as Ray's own handlers ended it (SIGINT: exit 0 and no word, as if
    it had finished; SIGTERM: ray.init's handler, exit 15)."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    run = tmp_path / "run"
    command = [sys.executable, "-m", "services.cli.main", "train", "pretrain", "--objective", "regression",
               "--data", str(tiny_train_data), "--run-dir", str(run), "--workers", "2", "--steps", "400",
               "--batch-size", "1", "--checkpoint-every", "2", "--object-store-mb", "100", "--device", "cpu"]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(command, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        while not list((run / "ray_train").glob("checkpoint_*/state.json")) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(getattr(signal, sig))
        out, err = proc.communicate(timeout=120)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    assert proc.returncode == 130, out[-2000:] + err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"n3dmap train: interrupted: stopped by {sig}") and "same command resumes" in last, last
    from services.training.checkpoints import is_complete

    newest = max((p for p in (run / "ray_train").glob("checkpoint_*") if is_complete(p)),
                 key=lambda p: read_checkpoint_state(p).step)
    assert f"its last checkpoint is at step {read_checkpoint_state(newest).step} ({newest})" in last
    assert not (run / "bundle").exists()
