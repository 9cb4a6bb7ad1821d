#!/usr/bin/env bash
# Session 31: does longer contrastive pretraining change few-label detection? Resumable (results.jsonl).
set -euo pipefail
cd /work/main
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
W=/work/bench-wt/out/bench-small/work
.venv/bin/python tests/benchmarks/bench_label_draws.py --work $W --heldout /work/exp/heldout-seed7 --heldout-seed 7 \
  --heldout-episodes 32 --out /work/exp/cont2400 --seeds 0 --arms contrastive regression --draws 0 1 2 3 --frozen \
  --continue-pretraining 2400 --threads 1
.venv/bin/python tests/benchmarks/bench_label_draws.py --work $W --heldout /work/exp/heldout-seed7 \
  --out /work/exp/cont-bench --seeds 0 --arms contrastive --draws 0 1 2 3 --frozen --threads 1
