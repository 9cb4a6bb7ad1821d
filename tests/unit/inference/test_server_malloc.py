"""services.malloc: n3dmap's long-running processes cap glibc's malloc arenas and keep their heap (see the
module doc for the measurements), unless the environment already decides; the settings hold for large
allocations made on other threads too (glibc then falls back to the main arena's heap)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
CODE = """
import threading
from services.malloc import keep_heap, limit_arenas
print(limit_arenas(), keep_heap())
import torch
out = []
def work():  # 96 MiB tensors on a thread, above glibc's largest mmap threshold, made and freed repeatedly
    for _ in range(3):
        out.append(float(torch.ones(24 * 1024 * 1024).sum()))
t = threading.Thread(target=work); t.start(); t.join()
print(out)
"""
CONTROLLED = ("MALLOC_ARENA_MAX", "MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_", "N3DMAP_MALLOC")


def _run(**env) -> list[str]:
    base = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    out = subprocess.run([sys.executable, "-c", CODE], cwd=ROOT, env={**base, "PYTHONPATH": str(ROOT), **env},
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_malloc_settings_apply_unless_the_environment_says():
    applied, sums = _run()
    assert applied == "True True"
    assert sums == str([float(24 * 1024 * 1024)] * 3)  # big allocations on a thread still work
    assert _run(MALLOC_ARENA_MAX="4")[0] == "False True"
    assert _run(MALLOC_MMAP_MAX_="65536")[0] == "True False"
    assert _run(N3DMAP_MALLOC="default")[0] == "False False"
