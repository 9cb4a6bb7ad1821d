#!/usr/bin/env bash
# Create .venv (if needed) and install n3dmap with its dev tools and the 3D viewer (rerun-sdk). Idempotent and quick when nothing
# changed: the install is skipped while pyproject.toml's hash matches the last successful install.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
. .venv/bin/activate
stamp=.venv/.n3dmap-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    python -m pip install -q --upgrade pip
    # torch first and pinned: anything that pulls an unpinned torch downloads GBs of CUDA wheels.
    python -m pip install -q "torch==2.13.0"
    python -m pip install -q -e ".[dev,viz]"
    echo "$want" > "$stamp"
fi
# Generated gRPC/protobuf stubs are committed; nothing to build here.
