"""What a Ray Train worker does with an error of ours (services.training.job.ray_train_func): a DataError — a bad
record, which reaches the one rank whose split holds it — is raised, so that Ray fails the whole worker group at
once (returned, it ended that rank alone while the others waited in their next collective for gloo's 30-minute
timeout: seen on a 2-worker run, which the old code had not ended after 150 s, and which ends in ~45 s now with
one line naming the record); other errors of ours (options, a checkpoint) are the same on every rank and end
the run as an error outcome, without Ray's retries."""

import pytest

import services.training.job as job
import services.training.sessions as sessions
from core.errors import DataError
from services.training.checkpoints import CheckpointError
from services.training.config import TrainJobConfig


@pytest.fixture
def worker(monkeypatch, tmp_path):
    monkeypatch.setattr(sessions, "RaySession", lambda config: None)   # no Ray here: the session is not used
    config = TrainJobConfig(task="pretrain", data_dir=str(tmp_path), run_dir=str(tmp_path / "run"), workers=2)

    def run(error: Exception):
        def train_loop(config, session, **kwargs):
            raise error
        monkeypatch.setattr(job, "train_loop", train_loop)
        return job.ray_train_func({"config": config.to_dict(), "threads": 1})
    return run


def test_a_bad_record_is_raised_to_fail_the_worker_group(worker):
    with pytest.raises(DataError, match="shard-00001.tar record ep000007"):
        worker(DataError("shard-00001.tar record ep000007: cannot decode npz"))


def test_an_error_every_rank_meets_ends_the_run_as_an_outcome(worker):
    outcome = worker(CheckpointError("checkpoint RUN/ray_train/checkpoint_00000004: missing state.json"))
    assert outcome["status"] == "error" and "missing state.json" in outcome["message"]
