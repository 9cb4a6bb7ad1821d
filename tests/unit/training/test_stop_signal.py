"""graceful_stop: SIGINT / SIGTERM become a flag inside the block; the old handlers come back after it."""

import os
import signal
import threading

import pytest

from services.training.stop_signal import graceful_stop


@pytest.fixture(autouse=True)
def sigint_as_at_a_terminal():
    """Python's own SIGINT handler for the test (restored after): a suite started in the background by a
    non-interactive shell inherits SIGINT ignored, which graceful_stop rightly leaves alone."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def test_the_first_signal_is_only_a_flag_and_the_handlers_come_back():
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    with graceful_stop() as stop_requested:
        assert stop_requested() is None
        os.kill(os.getpid(), signal.SIGTERM)   # delivered to the main thread before kill returns here
        assert stop_requested() == "SIGTERM"
        os.kill(os.getpid(), signal.SIGTERM)   # already stopping: nothing more
        assert stop_requested() == "SIGTERM"
    assert {sig: signal.getsignal(sig) for sig in before} == before


def test_a_second_ctrl_c_stops_at_once():
    with pytest.raises(KeyboardInterrupt):
        with graceful_stop() as stop_requested:
            os.kill(os.getpid(), signal.SIGINT)
            assert stop_requested() == "SIGINT"
            os.kill(os.getpid(), signal.SIGINT)
            pytest.fail("the second SIGINT did not interrupt")


def test_outside_the_main_thread_nothing_is_installed():
    seen = {}

    def worker():
        with graceful_stop() as stop_requested:
            seen["handler"] = signal.getsignal(signal.SIGTERM)
            seen["requested"] = stop_requested()

    before = signal.getsignal(signal.SIGTERM)
    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen == {"handler": before, "requested": None}


def test_an_ignored_signal_stays_ignored():
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job's SIGINT is
    try:
        with graceful_stop() as stop_requested:
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGINT)
            assert stop_requested() is None
            os.kill(os.getpid(), signal.SIGTERM)
            assert stop_requested() == "SIGTERM"
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def test_a_signal_while_the_handlers_go_in_leaves_none_of_them_behind(monkeypatch):
    # the old SIGTERM handler raises as graceful_stop installs its own (a signal that lands in between):
    # the SIGINT handler it had already installed must not stay
    real_signal = signal.signal
    before = signal.getsignal(signal.SIGINT)

    def install(sig, handler):
        if sig == signal.SIGTERM and handler not in (signal.SIG_DFL, signal.SIG_IGN) and callable(handler):
            if getattr(handler, "__name__", "") == "handle":
                raise KeyboardInterrupt  # as the old handler would, run by a pending SIGTERM
        return real_signal(sig, handler)

    monkeypatch.setattr(signal, "signal", install)
    with pytest.raises(KeyboardInterrupt):
        with graceful_stop():
            pytest.fail("the block ran")
    assert signal.getsignal(signal.SIGINT) is before
