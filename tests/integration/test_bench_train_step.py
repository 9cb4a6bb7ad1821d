"""The per-task mode of tests/benchmarks/bench_train_step.py keeps working: one task on tiny, one timed
step, in its row subprocess; the JSON row it prints has every field, and the table follows (~6 s)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def test_per_task_mode_prints_one_json_row_and_a_table():
    args = [sys.executable, str(ROOT / "tests/benchmarks/bench_train_step.py"), "--tasks", "egomotion",
            "--preset", "tiny", "--threads", "1", "--steps", "1", "--warmup", "0", "--profile-steps", "1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    rows = [json.loads(x) for x in proc.stdout.splitlines() if x.startswith("{")]
    assert len(rows) == 1
    row = rows[0]
    assert {"task", "preset", "threads", "steps", "step_s_median", "step_s_mean", "conv_share", "peak_rss_mb",
            "top_non_conv", "load_avg"} <= set(row)
    assert (row["task"], row["preset"], row["threads"], row["steps"]) == ("egomotion", "tiny", 1, 1)
    assert row["step_s_median"] > 0 and 0 < row["conv_share"] < 1 and row["peak_rss_mb"] > 0
    assert len(row["load_avg"]) == 3 and 0 < len(row["top_non_conv"]) <= 5
    assert "aten::convolution_backward" in row["conv_ops"]
    assert "top non-conv op" in proc.stdout  # the table header


def test_per_task_mode_refuses_unknown_tasks_and_the_paper_preset():
    script = str(ROOT / "tests/benchmarks/bench_train_step.py")
    for extra in (["--tasks", "nope", "--preset", "tiny"], ["--tasks", "flow", "--preset", "paper"]):
        proc = subprocess.run([sys.executable, script, *extra], cwd=ROOT, capture_output=True, text=True,
                              timeout=60, env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert proc.returncode != 0 and ("unknown task" in proc.stderr or "CPU presets" in proc.stderr)
