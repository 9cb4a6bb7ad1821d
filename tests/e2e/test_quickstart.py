"""The README's main job, end to end, at the smallest size that still runs every step.

Real processes throughout: the `n3dmap` CLI for data, a 2-worker local Ray for pretraining, the
downstream training jobs, `eval all`, a real `n3dmap serve` called over REST and gRPC, and the zenoh
bridge fed by the simulated camera with a listener. It checks what the job leaves behind and what it
prints, not the quality of 2-step models.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from core.bundle import read_bundle_meta

pytestmark = [pytest.mark.slow, pytest.mark.integration]

ROOT = Path(__file__).resolve().parents[2]


def test_main_job_runs_every_step(tmp_path):
    out = tmp_path / "quickstart"
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run([sys.executable, "-m", "services.quickstart", "--out", str(out), "--episodes", "4",
                           "--steps", "2"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=1500)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert "Traceback" not in log, log[-4000:]

    # 1. data and preview
    for split in ("train", "val"):
        assert json.loads((out / "data" / split / "manifest.json").read_text())["split"] == split
    assert (out / "preview.png").stat().st_size > 10_000
    # 2-3. every training run exported a bundle; the last one holds every module of the chain
    for task in ("pretrain", "egomotion", "occupancy", "flow", "detector"):
        assert (out / "runs" / task / "bundle" / "weights.safetensors").is_file(), task
        assert (out / "runs" / task / "metrics.jsonl").read_text().strip(), task
    modules = set(read_bundle_meta(out / "runs" / "detector" / "bundle")["modules"])
    assert {"mapper", "projector", "occupancy", "egomotion", "flow", "detector"} <= modules
    # 4. evaluation report
    metrics = json.loads((out / "reports" / "all" / "metrics.json").read_text())
    assert (out / "reports" / "all" / "report.md").is_file() and metrics
    # 5. both transports answered every route
    for transport in ("REST", "gRPC"):
        for route in ("map", "egomotion", "flow", "detect", "moving-objects"):
            assert f"{transport} {route}:" in log, (transport, route)
    # 6. the bridge processed frames and its accounting balanced
    line = next(l for l in log.splitlines() if "bridge accounting for cam0" in l)
    numbers = dict(part.strip().rsplit(" ", 1) for part in line.split(":", 1)[1].split(";")[0].split(","))
    received, processed, dropped, malformed, errors = (
        int(numbers[k]) for k in ("received", "processed", "dropped", "malformed", "errors"))
    assert received == 16 and processed >= 2 and malformed == errors == 0
    assert received == processed + dropped + malformed + errors
    # ... and, with the viz extra, `stream view` recorded one detections entry per processed frame
    import importlib.util
    if importlib.util.find_spec("rerun") is not None:
        assert (out / "stream.rrd").stat().st_size > 100_000
        assert f"{processed} detection messages" in next(l for l in log.splitlines() if "viewer: logged" in l)
