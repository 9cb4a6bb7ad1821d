#!/usr/bin/env bash
# Continue the small report on a fresh machine: set up, unpack the carried state, start the same command
# from a worktree of COMMIT (default: HEAD) in the background. Log: out/bench-small.log.
#   bash .bench-carry/resume.sh [COMMIT]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh > /dev/null
mkdir -p out
.venv/bin/python .bench-carry/carry.py unpack out/bench-small
commit="${1:-HEAD}"
rm -rf /work/bench-wt
git worktree prune
git worktree add --detach /work/bench-wt "$commit" > /dev/null
ln -sfn "$PWD/.venv" /work/bench-wt/.venv
cat > out/bench-small.sh <<EOS
#!/usr/bin/env bash
cd /work/bench-wt
export OMP_NUM_THREADS=1 RAY_USAGE_STATS_ENABLED=0 PYTHONUNBUFFERED=1
exec $PWD/.venv/bin/n3dmap bench paper --preset small --out $PWD/out/bench-small --seeds 3 --parallel-seeds 3 \\
  --task-options '{"mapper": {"encoder_full_res": 16}, "pretrain": {"coeff_match": 1.0, "coeff_occ": 3.0}, "flow_features": {"refine_radius": [3, 1, 3], "refine_aggregate": [1, 1, 1]}}'
EOS
chmod +x out/bench-small.sh
nohup out/bench-small.sh >> out/bench-small.log 2>&1 &
echo "started pid $! at $(date -u +%H:%M) from $(git -C /work/bench-wt rev-parse --short HEAD); log out/bench-small.log"
