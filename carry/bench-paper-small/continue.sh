#!/usr/bin/env bash
# Continue the small report's regeneration (issue 13, item 8) on this machine, from the carry beside this file
# if the run's work directory is not here yet. Run from a git worktree of the repository (so that edits to the
# main checkout never reach the running workers), with the main checkout's .venv set up (scripts/setup.sh):
#
#     git worktree add /work/bench-wt HEAD && bash /work/bench-wt/carry/bench-paper-small/continue.sh
#
# Stop it with SIGTERM to the `bench paper` process (its stages save a checkpoint at the step they are in),
# then save from the main checkout: `n3dmap bench carry save --out /work/bench-wt/out/bench-small --to
# carry/bench-paper-small` and commit the folder.
#
# `--threads 1`: the run started with one torch thread per seed worker (3 workers on 2 CPUs); without it a machine
# with more CPUs would give the resumed workers more threads, and float sums in another order than an
# uninterrupted run's.
set -euo pipefail
tree=$(cd "$(dirname "$0")/../.." && pwd)
venv=${N3DMAP_VENV:-/work/main/.venv}
cd "$tree"
export PYTHONPATH="$tree" OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=disabled PYTHONUNBUFFERED=1
if [[ ! -d out/bench-small/work ]]; then
    "$venv/bin/python" -m services.cli.main bench carry restore --from carry/bench-paper-small --out out/bench-small
fi
exec "$venv/bin/python" -m services.cli.main bench paper --preset small --out out/bench-small --seeds 3 --parallel-seeds 3 --threads 1 \
  --rerun-changed --task-options '{"mapper": {"encoder_full_res": 16}, "pretrain": {"coeff_match": 1.0, "coeff_occ": 3.0},
  "pretrain_contrastive": {"shift_positives": 3}, "flow_features": {"refine_radius": [3, 1, 3], "refine_aggregate": [1, 1, 1]}}'
