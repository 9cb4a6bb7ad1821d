"""`n3dmap data` as a user runs it: real subprocesses, exit codes, one-line errors (no traceback)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def n3dmap(*args, timeout=300) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "services.cli.main", "data", *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=timeout)


def assert_one_line_error(proc: subprocess.CompletedProcess, *fragments: str) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("n3dmap data: error: "), lines[0]
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """8 tiny synthetic records in ~1 MB shards (several shards), generated once for the module."""
    out = tmp_path_factory.mktemp("data") / "d"
    proc = n3dmap("generate", "--preset", "tiny", "--episodes", 8, "--seed", 5, "--out", out,
                  "--shard-mb", 1, "--moving-ego", "mixed")
    assert proc.returncode == 0, proc.stderr
    assert "wrote 8 records" in proc.stdout
    return out


def test_generate_writes_a_manifest(dataset):
    manifest = json.loads((dataset / "manifest.json").read_text())
    assert manifest["num_records"] == 8 and manifest["preset"] == "tiny" and manifest["seed"] == 5
    assert len(manifest["shards"]) > 1
    assert manifest["generator"]["moving_ego"] == "mixed"
    assert manifest["dims"]["T"] == [2, 2] and manifest["dims"]["V"] == [3, 3]


def test_info_verify_and_preview(dataset, tmp_path):
    proc = n3dmap("info", dataset, "--verify")
    assert proc.returncode == 0, proc.stderr
    assert "records    8 in" in proc.stdout and "verified   8 records" in proc.stdout

    png = tmp_path / "sheet.png"
    proc = n3dmap("preview", dataset, "--out", png, "--index", 3)
    assert proc.returncode == 0, proc.stderr
    with Image.open(png) as img:
        pixels = np.asarray(img.convert("RGB"))
    assert pixels.shape[0] > 200 and pixels.std() > 10          # a real picture, not a blank canvas


def test_corrupt_datasets_fail_with_one_line(dataset, tmp_path):
    # More error cases run in-process in tests/unit/data/test_data_cli_errors.py (each subprocess here
    # pays the CLI's start-up imports).
    bad = tmp_path / "flipped"
    shutil.copytree(dataset, bad)
    shard = bad / "shard-00001.tar"
    data = bytearray(shard.read_bytes())
    data[len(data) // 3] ^= 0x55
    shard.write_bytes(bytes(data))
    assert_one_line_error(n3dmap("info", bad, "--verify"), "shard-00001.tar", "sha256 mismatch")

    short = tmp_path / "truncated"
    shutil.copytree(dataset, short)
    shard = short / "shard-00000.tar"
    shard.write_bytes(shard.read_bytes()[:100_000])
    assert_one_line_error(n3dmap("preview", short, "--out", tmp_path / "x.png"), "shard-00000.tar", "truncated")
