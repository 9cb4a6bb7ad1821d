"""`n3dmap serve` caps glibc's malloc arenas (RSS crept up under concurrent load without it), unless
MALLOC_ARENA_MAX already decides."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
CODE = "from services.inference.server import limit_malloc_arenas; print(limit_malloc_arenas())"


def _run(**env) -> str:
    base = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    out = subprocess.run([sys.executable, "-c", CODE], cwd=ROOT, env={**base, "PYTHONPATH": str(ROOT), **env},
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_serve_caps_malloc_arenas_unless_the_environment_says():
    assert _run() == "True"
    assert _run(MALLOC_ARENA_MAX="4") == "False"
