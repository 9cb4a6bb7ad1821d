"""Progress of a run: one console line and one metrics.jsonl line per logged step.

Only the rank-0 worker logs. metrics.jsonl is appended to, so a resumed run continues the same
file; each line carries the step, wall time, attempt number and the losses/metrics averaged over
workers.
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


class ProgressLogger:
    """Prints progress lines and appends JSON lines to `metrics_path` (rank 0 only)."""

    def __init__(self, *, metrics_path: str | Path, total_steps: int, start_step: int, attempt: int,
                 stream: TextIO | None = None, clock=time.monotonic) -> None:
        self.metrics_path = Path(metrics_path)
        self.metrics_path.parent.mkdir(parents=True, exist_ok=True)
        self.total_steps = total_steps
        self.attempt = attempt
        self.stream = stream if stream is not None else sys.stdout
        self.meter = RateMeter(start_step=start_step, clock=clock)

    def log(self, step: int, metrics: dict[str, float]) -> dict:
        """Record one step; returns the JSON record written."""
        rate = self.meter.rate(step)
        eta = self.meter.eta(step, self.total_steps)
        record = {"step": step, "time": time.time(), "attempt": self.attempt,
                  **{k: float(v) for k, v in metrics.items()},
                  "steps_per_s": rate if math.isfinite(rate) else None}
        with self.metrics_path.open("a") as f:
            f.write(json.dumps(record, allow_nan=True) + "\n")
        print(format_progress(step=step, total_steps=self.total_steps, metrics=metrics,
                              steps_per_s=rate, eta_s=eta), file=self.stream, flush=True)
        return record


def read_metrics(path: str | Path) -> list[dict]:
    """All records of a metrics.jsonl file (an empty list if it does not exist)."""
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
