"""Progress of a run: one console line and one metrics.jsonl line per logged step.

Only the rank-0 worker logs. metrics.jsonl is appended to, so a resumed run continues the same
file; each line carries the step, wall time, the step this attempt started from, rate, ETA and
the losses/metrics averaged over workers.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import TextIO


def format_duration(seconds: float) -> str:
    """`75.2` → `1m15s`; `3725` → `1h02m`; non-finite → `?`."""
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds}s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes}m{seconds:02d}s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m"


def format_value(value: float) -> str:
    """Four significant digits, scientific only for very small/large magnitudes."""
    if value != 0 and (abs(value) < 1e-3 or abs(value) >= 1e5):
        return f"{value:.3e}"
    return f"{value:.4g}"


def format_progress(*, step: int, total_steps: int, metrics: dict[str, float],
                    steps_per_s: float, eta_s: float) -> str:
    """One console line: `step 12/200 (6%)  loss 0.5321  l3d 0.31  2.41 steps/s  ETA 1m18s`.

    `loss` comes first, then the other metrics in name order.
    """
    width = len(str(total_steps))
    percent = 100.0 * step / total_steps if total_steps else 100.0
    names = (["loss"] if "loss" in metrics else []) + sorted(k for k in metrics if k != "loss")
    values = "  ".join(f"{k} {format_value(metrics[k])}" for k in names)
    rate = f"{steps_per_s:.2f} steps/s" if math.isfinite(steps_per_s) else "? steps/s"
    return (f"step {step:>{width}}/{total_steps} ({percent:3.0f}%)  {values}  {rate}  "
            f"ETA {format_duration(eta_s)}")


class RateMeter:
    """Steps per second over the steps since the meter started (resumed runs restart it)."""

    def __init__(self, *, start_step: int, clock=time.monotonic) -> None:
        self._clock = clock
        self._start_step = start_step
        self._start_time = clock()

    def rate(self, step: int) -> float:
        elapsed = self._clock() - self._start_time
        done = step - self._start_step
        return done / elapsed if elapsed > 0 and done > 0 else float("nan")

    def eta(self, step: int, total_steps: int) -> float:
        rate = self.rate(step)
        return (total_steps - step) / rate if rate > 0 else float("nan")


# Keys of a metrics.jsonl record that are bookkeeping, not losses/metrics of the task.
RECORD_KEYS = ("step", "total_steps", "time", "start_step", "steps_per_s", "eta_s")


class ProgressLogger:
    """Appends one JSON line per logged step to `metrics_path` and, if `stream` is given, prints
    the progress line there too (rank 0 only). Ray workers pass no stream: the driver prints the
    lines it reads back from metrics.jsonl (`MetricsTail`), which keeps Ray's own logs off the console.
    """

    def __init__(self, *, metrics_path: str | Path, total_steps: int, start_step: int,
                 stream: TextIO | None = None, clock=time.monotonic) -> None:
        self.metrics_path = Path(metrics_path)
        self.metrics_path.parent.mkdir(parents=True, exist_ok=True)
        self.total_steps = total_steps
        self.start_step = start_step
        self.stream = stream
        self.meter = RateMeter(start_step=start_step, clock=clock)

    def log(self, step: int, metrics: dict[str, float]) -> dict:
        """Record one step; returns the JSON record written."""
        rate = self.meter.rate(step)
        eta = self.meter.eta(step, self.total_steps)
        record = {"step": step, "total_steps": self.total_steps, "time": time.time(),
                  "start_step": self.start_step,
                  "steps_per_s": rate if math.isfinite(rate) else None,
                  "eta_s": eta if math.isfinite(eta) else None,
                  **{k: float(v) for k, v in metrics.items()}}
        with self.metrics_path.open("a") as f:
            f.write(json.dumps(record, allow_nan=True) + "\n")
        if self.stream is not None:
            print(format_record(record), file=self.stream, flush=True)
        return record


def format_record(record: dict) -> str:
    """The console line of one metrics.jsonl record."""
    nan = float("nan")
    metrics = {k: v for k, v in record.items() if k not in RECORD_KEYS and isinstance(v, (int, float))}
    rate = record.get("steps_per_s")
    eta = record.get("eta_s")
    return format_progress(step=record["step"], total_steps=record.get("total_steps", record["step"]),
                           metrics=metrics, steps_per_s=nan if rate is None else rate,
                           eta_s=nan if eta is None else eta)


class MetricsTail:
    """Prints the lines appended to a metrics.jsonl file while a run is going (driver side).

    `poll()` prints what is new since the last call; `run_in_thread()` polls until `stop()`. A new
    `start_step` in the records (a retry from a checkpoint, or a resumed run) gets its own line.
    """

    def __init__(self, path: str | Path, *, stream: TextIO | None = None) -> None:
        self.path = Path(path)
        self.stream = stream if stream is not None else sys.stdout
        self._offset = self.path.stat().st_size if self.path.is_file() else 0
        self._start_step: int | None = None
        self._stop = None
        self._thread = None

    def poll(self) -> int:
        if not self.path.is_file():
            return 0
        with self.path.open("rb") as f:
            f.seek(self._offset)
            data = f.read()
        complete = data[: data.rfind(b"\n") + 1]  # a line still being written waits for the next poll
        self._offset += len(complete)
        count = 0
        for line in complete.decode().splitlines():
            if not line.strip():
                continue
            record = json.loads(line)
            start = record.get("start_step")
            if start != self._start_step and start:
                print(f"workers (re)started from the checkpoint at step {start}", file=self.stream, flush=True)
            self._start_step = start
            print(format_record(record), file=self.stream, flush=True)
            count += 1
        return count

    def run_in_thread(self, interval_s: float = 0.5) -> "MetricsTail":
        import threading

        self._stop = threading.Event()

        def loop() -> None:
            while not self._stop.wait(interval_s):
                self.poll()

        self._thread = threading.Thread(target=loop, name="metrics-tail", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self._thread = None
        self.poll()


def read_metrics(path: str | Path) -> list[dict]:
    """All records of a metrics.jsonl file (an empty list if it does not exist)."""
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
