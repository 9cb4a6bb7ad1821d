"""One seed of `n3dmap bench paper`, in its own process (the parent runs several at once).

    python -m services.bench.seed_worker --out REPORT_DIR --seed S --threads T

Reads the plan the parent wrote (REPORT_DIR/work/plan.json), sets T torch threads before any work
(the parent chose T so that processes × threads fits the usable CPUs), and runs every stage of seed S
(services.bench.paper.run_one_seed). Finished stages are skipped, so a rerun resumes. Exit status 0 on
success; 2 with one line naming the problem otherwise.
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.bench.seed_worker", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="the benchmark's REPORT_DIR")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--threads", type=int, required=True, help="torch threads of this process")
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")

    import torch

    from core.errors import N3dmapError
    from services.bench.paper import run_one_seed

    torch.set_num_threads(args.threads)
    print(f"[bench] seed {args.seed} worker: {args.threads} torch thread(s)", flush=True)
    try:
        run_one_seed(args.out, args.seed, log=lambda line: print(line, flush=True))
    except (N3dmapError, OSError) as e:
        print(f"error: seed {args.seed}: {e}", file=sys.stderr, flush=True)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
