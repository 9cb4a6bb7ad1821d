#!/usr/bin/env bash
# The main job, end to end on the embedded defaults: synthetic data, a local Ray, local services.
# Everything lands under ./quickstart/ (override with N3DMAP_QUICKSTART_DIR).
#   1. generate a tiny synthetic RGB-D dataset (train + val) and write its preview
#   2. pretrain the neural 3D mapper view-contrastively on a 2-worker local Ray
#   3. train egomotion, occupancy, 3D flow and a detector on top of it (each job warm-starts from the last bundle)
#   4. evaluate them and write reports
#   5. serve the bundle over REST + gRPC and call every route
#   6. stream a simulated camera through the zenoh bridge and print moving-object detections
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
export RAY_USAGE_STATS_ENABLED=0 RAY_AUTH_MODE=disabled PYTHONUNBUFFERED=1
exec python -m services.quickstart --out "${N3DMAP_QUICKSTART_DIR:-quickstart}" "$@"
