"""The soak benchmark (tests/benchmarks/bench_soak.py) keeps working: a real server, a few schemathesis cases
and a few seconds of mixed REST + gRPC load, with the JSON summary it prints; and its verdict on outcomes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.benchmarks.bench_soak import summarise_load

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def test_soak_harness_runs_end_to_end_with_tiny_numbers():
    args = [sys.executable, str(ROOT / "tests/benchmarks/bench_soak.py"), "--cases", "30", "--phases",
            "examples,fuzzing", "--clients", "4", "--seconds", "3", "--warmup", "1",
            "--max-rss-growth", "50"]  # RSS is noise over 2 s; the full soak holds it to 5 %
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=180, env=env)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    line = next(x for x in proc.stdout.splitlines() if x.startswith("SOAK_JSON "))
    summary = json.loads(line[len("SOAK_JSON "):])
    assert summary["ok"] and summary["server_exit"] == 0
    fuzz, load = summary["fuzz"], summary["load"]
    assert fuzz["cases"] >= 30 and fuzz["server_errors"] == 0 and "5xx" not in fuzz["by_class"]
    assert load["total_requests"] > 0 and not load["disallowed"]
    assert {k.split()[0] for k in load["status"]} == {"REST", "gRPC"}  # both transports were exercised
    assert load["window"]["all"]["ok"] > 0 and load["window"]["all"]["p50_ms"] > 0
    assert load["rss_mb"]["end"] > 0 and len(load["loadavg_after"]) == 3
    for figure in ("p50", "p99", "server RSS", "load average", "responses by class"):
        assert figure in proc.stdout, figure


def test_only_2xx_and_429_pass_the_load_verdict_and_rss_growth_compares_window_medians():
    MiB = 2**20
    # RSS over 0..3 s after a 0 s warm-up: 1 s windows; a spike at the end point alone moves the median little
    rss = [(0.0, 100 * MiB), (0.5, 140 * MiB), (1.0, 100 * MiB), (2.0, 110 * MiB), (2.5, 110 * MiB), (3.0, 200 * MiB)]

    def raw(records):
        return {"records": records, "failures": [], "rss": rss, "rss_start": 90 * MiB, "rss_warm": 100 * MiB,
                "warm_t": 0.0, "rss_end": 200 * MiB, "elapsed": 3.0, "load_before": (0.0,) * 3,
                "load_after": (0.0,) * 3}

    allowed = [(0.5, "REST", "/v1/map", "200", 0.1), (0.5, "REST", "/v1/map", "429", 0.01),
               (0.5, "gRPC", "Map", "OK", 0.1), (0.5, "gRPC", "Map", "RESOURCE_EXHAUSTED", 0.01)]
    assert summarise_load(raw(allowed), clients=2, warmup=0)["disallowed"] == {}
    refused = [(0.5, "REST", "/v1/map", "500", 0.1), (0.5, "REST", "/v1/flow", "504", 0.1),
               (0.5, "REST", "/v1/map", "ReadTimeout", 60.0), (0.5, "gRPC", "Map", "DEADLINE_EXCEEDED", 30.0),
               (0.5, "gRPC", "Map", "INTERNAL", 0.1), (0.5, "REST", "/v1/map", "422", 0.1)]
    assert set(summarise_load(raw(allowed + refused), clients=2, warmup=0)["disallowed"]) == {
        "REST 500", "REST 504", "REST ReadTimeout", "gRPC DEADLINE_EXCEEDED", "gRPC INTERNAL", "REST 422"}
    ld = summarise_load(raw(allowed), clients=2, warmup=0)
    assert ld["rss_window_s"] == 1.0 and ld["rss_growth_pct"] == pytest.approx(10.0)  # medians 100 -> 110 MiB
    assert ld["rss_growth_point_pct"] == pytest.approx(100.0) and ld["rss_mb"]["peak"] == 200
