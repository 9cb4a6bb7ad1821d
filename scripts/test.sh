#!/usr/bin/env bash
# Set up and run the whole test suite (unit, integration, e2e). Extra arguments go to pytest, e.g.
# `bash scripts/test.sh -m "not slow"`, or `bash scripts/test.sh tests/unit/geometry -x` for one folder.
# pytest's exit status is passed on unchanged, so "no tests collected" (exit 5) fails too.
#
# The suite runs in N3DMAP_TEST_WORKERS pytest processes (pytest-xdist; default 2, 0 = one process), each
# test file whole on one of them (`--dist loadfile`: a file's module fixtures are built once). Why: half the
# suite waits on processes it starts (Ray, servers, CLI runs), so two processes keep a 2-core machine busy
# (757 → 507 s here). Each runs torch on one thread, so two never spin against each other.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=disabled PYTHONUNBUFFERED=1
workers=${N3DMAP_TEST_WORKERS:-2}
if ! [[ "$workers" =~ ^[0-9]+$ ]]; then
    echo "scripts/test.sh: N3DMAP_TEST_WORKERS must be a whole number (0 = one process), got '$workers'" >&2
    exit 2
fi
parallel=()
if (( workers > 1 )); then
    parallel=(-n "$workers" --dist loadfile)
    export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1}
fi
# Paths among the arguments (existing files or folders, e.g. tests/unit/geometry) replace the default `tests`.
targets=(tests)
for arg in "$@"; do
    if [[ "$arg" != -* && -e "$arg" ]]; then targets=(); break; fi
done
exec python -m pytest "${targets[@]}" -q "${parallel[@]}" "$@"
