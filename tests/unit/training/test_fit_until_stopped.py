"""services.training.job._fit_until_stopped: Ray's fit() runs off the main thread (where Ray installs its own
SIGINT handler, which ended a Ctrl-C'd run with exit 0), its result or error comes back to the caller, and a stop
request ends the wait while fit() is still running — but not a fit() that already finished."""

import threading
import time

import pytest

from services.training.job import _fit_until_stopped


class Trainer:
    def __init__(self, *, seconds: float = 0.0, error: Exception | None = None):
        self.seconds, self.error, self.thread = seconds, error, None

    def fit(self):
        self.thread = threading.current_thread()
        time.sleep(self.seconds)
        if self.error is not None:
            raise self.error
        return "result"


def test_fit_runs_off_the_main_thread_and_hands_back_its_result_or_error():
    trainer = Trainer()
    assert _fit_until_stopped(trainer, lambda: None) == "result"
    assert trainer.thread is not threading.main_thread()
    with pytest.raises(ValueError, match="worker failed"):
        _fit_until_stopped(Trainer(error=ValueError("worker failed")), lambda: None)


def test_a_stop_request_ends_the_wait_but_not_a_finished_fit():
    started = time.monotonic()
    assert _fit_until_stopped(Trainer(seconds=30.0), lambda: "SIGTERM") is None   # fit still running: stopped
    assert time.monotonic() - started < 5.0
    assert _fit_until_stopped(Trainer(), lambda: "SIGINT") == "result"   # done before the first check: kept
