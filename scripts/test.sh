#!/usr/bin/env bash
# Set up and run the whole test suite (unit, integration, e2e). Extra arguments go to pytest, e.g.
# `bash scripts/test.sh -m "not slow"`, or `bash scripts/test.sh tests/unit/geometry -x` for one folder.
# pytest's exit status is passed on unchanged, so "no tests collected" (exit 5) fails too.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=disabled PYTHONUNBUFFERED=1
# Paths among the arguments (existing files or folders, e.g. tests/unit/geometry) replace the default `tests`.
targets=(tests)
for arg in "$@"; do
    if [[ "$arg" != -* && -e "$arg" ]]; then targets=(); break; fi
done
exec python -m pytest "${targets[@]}" -q "$@"
