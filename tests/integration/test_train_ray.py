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


def test_rerun_resumes_at_the_saved_step_and_sigterm_ends_it_as_an_interruption(killed_run):
    """Rerunning the command with more steps resumes at the saved step (not from 0); SIGTERM (`kill`, `ray job
    stop`) once it has saved a newer checkpoint ends the run with exit 130 and one line naming that checkpoint —
    not ray.init's own handler's exit 15 or fit()'s SIGINT handler's silent exit 0 (the signal path's stop loop and
    fit() off the main thread: tests/unit/training/test_fit_until_stopped.py). One Ray run for both: each costs
    ~60 s of a 2-core CI machine."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from services.training.checkpoints import is_complete

    config, _ = killed_run
    root = Path(__file__).resolve().parents[2]
    ray_root = Path(config.run_dir) / "ray_train"
    command = [sys.executable, "-m", "services.cli.main", "train", "pretrain", "--objective", "regression",
               "--data", config.data_dir, "--run-dir", config.run_dir, "--workers", "2", "--steps", "400",
               "--batch-size", "1", "--checkpoint-every", "2", "--log-every", "1", "--object-store-mb", "100",
               "--device", "cpu"]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}

    def newest() -> int:
        steps = [read_checkpoint_state(p).step for p in ray_root.glob("checkpoint_*") if is_complete(p)]
        return max(steps, default=0)

    proc = subprocess.Popen(command, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)   # its own process group: the embedded Ray goes with it
    try:
        deadline = time.monotonic() + 240
        while newest() <= 4 and time.monotonic() < deadline:
            time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    assert proc.returncode == 130, out[-2000:] + err[-2000:]
    # the driver prints the workers' progress (read back from metrics.jsonl), not Ray's logs
    assert "workers (re)started from the checkpoint at step 4" in out, out[-2000:]
    assert [r["step"] for r in read_metrics(config.metrics_path) if r["start_step"] == 4][:2] == [5, 6]
    last = err.strip().splitlines()[-1]
    saved = max((p for p in ray_root.glob("checkpoint_*") if is_complete(p)), key=lambda p: read_checkpoint_state(p).step)
    assert last.startswith("n3dmap train: interrupted: stopped by SIGTERM") and "same command resumes" in last, last
    assert f"its last checkpoint is at step {read_checkpoint_state(saved).step} ({saved})" in last, last
