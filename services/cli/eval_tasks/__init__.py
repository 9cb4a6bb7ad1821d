"""One module per evaluation kind: `register(kind_subparsers)` adds `n3dmap eval <kind>` (see services/cli/eval.py)."""
