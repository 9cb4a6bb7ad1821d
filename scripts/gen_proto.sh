#!/usr/bin/env bash
# Regenerate the Python protobuf/gRPC stubs from proto/n3dmap/v1/*.proto.
#
# The include root is proto/, so the generated imports are package paths that mirror the proto
# package: `from n3dmap.v1 import types_pb2`. (A Python package named `proto` would collide with
# the `proto-plus` distribution that google-api-core, pulled in by ray[default], installs as `proto`.)
# Usage: scripts/gen_proto.sh [OUT_DIR]   (default: the repo root; tests pass a temp dir and compare)
# PYTHON names the interpreter that has grpcio-tools (default: python on PATH, e.g. the activated venv).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-.}
mkdir -p "$out/n3dmap/v1"
"${PYTHON:-python}" -m grpc_tools.protoc -I proto \
    --python_out="$out" --pyi_out="$out" --grpc_python_out="$out" \
    proto/n3dmap/v1/types.proto proto/n3dmap/v1/inference.proto
