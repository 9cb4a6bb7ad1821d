"""Progress formatting and the metrics.jsonl logger."""

import io
import json

from services.training.progress import (
    ProgressLogger, RateMeter, format_duration, format_progress, read_metrics,
)


def test_format_duration():
    assert format_duration(0) == "0s"
    assert format_duration(59.4) == "59s"
    assert format_duration(75.2) == "1m15s"
    assert format_duration(3725) == "1h02m"
    assert format_duration(float("nan")) == "?"
    assert format_duration(float("inf")) == "?"


def test_format_progress_puts_loss_first_and_shows_rate_and_eta():
    line = format_progress(step=12, total_steps=200, metrics={"l3d": 0.31, "loss": 0.53214, "acc": 0.9},
                           steps_per_s=2.4, eta_s=78.3)
    assert line == "step  12/200 (  6%)  loss 0.5321  acc 0.9  l3d 0.31  2.40 steps/s  ETA 1m18s"
    unknown = format_progress(step=1, total_steps=5, metrics={"loss": 1e-5}, steps_per_s=float("nan"),
                              eta_s=float("nan"))
    assert unknown == "step 1/5 ( 20%)  loss 1.000e-05  ? steps/s  ETA ?"


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_rate_meter_counts_steps_since_start():
    clock = FakeClock()
    meter = RateMeter(start_step=10, clock=clock)
    clock.t += 4.0
    assert meter.rate(18) == 2.0
    assert meter.eta(18, 28) == 5.0


def test_logger_appends_one_json_line_per_logged_step(tmp_path):
    clock = FakeClock()
    out = io.StringIO()
    path = tmp_path / "run" / "metrics.jsonl"
    logger = ProgressLogger(metrics_path=path, total_steps=4, start_step=0, stream=out, clock=clock)
    for step in (1, 2):
        clock.t += 0.5
        logger.log(step, {"loss": 1.0 / step})
    # A resumed run appends to the same file.
    ProgressLogger(metrics_path=path, total_steps=4, start_step=2, stream=out,
                   clock=clock).log(3, {"loss": 0.25})
    records = read_metrics(path)
    assert [r["step"] for r in records] == [1, 2, 3]
    assert [r["loss"] for r in records] == [1.0, 0.5, 0.25]
    assert records[1]["steps_per_s"] == 2.0 and records[2]["start_step"] == 2
    assert all(json.loads(line) for line in path.read_text().splitlines())
    assert out.getvalue().count("\n") == 3 and "step 2/4" in out.getvalue()


def test_tail_prints_new_complete_lines_once(tmp_path):
    from services.training.progress import MetricsTail, format_record

    path = tmp_path / "metrics.jsonl"
    out = io.StringIO()
    tail = MetricsTail(path, stream=out)
    assert tail.poll() == 0  # no file yet
    first = {"step": 1, "total_steps": 4, "start_step": 0, "steps_per_s": None, "eta_s": None, "loss": 2.0}
    path.write_text(json.dumps(first) + "\n" + '{"step": 2, "tot')  # second line half written
    assert tail.poll() == 1
    with path.open("a") as f:
        f.write('al_steps": 4, "start_step": 0, "steps_per_s": 1.0, "eta_s": 2.0, "loss": 1.0}\n')
        f.write(json.dumps(dict(first, step=3, start_step=2)) + "\n")
    assert tail.poll() == 2
    lines = out.getvalue().splitlines()
    assert lines[0] == format_record(first)
    assert lines[1].startswith("step 2/4 ( 50%)  loss 1  1.00 steps/s  ETA 2s")
    assert lines[2] == "workers (re)started from the checkpoint at step 2"
    assert tail.poll() == 0
