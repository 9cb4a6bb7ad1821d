"""One seed of `n3dmap bench paper`, in its own process (the parent runs several at once).

    python -m services.bench.seed_worker --out REPORT_DIR --seed S --threads T

Reads the plan the parent wrote (REPORT_DIR/work/plan.json), sets T torch threads before any work
(the parent chose T so that processes × threads fits the usable CPUs), and runs every stage of seed S
(services.bench.paper.run_one_seed). Finished stages are skipped, so a rerun resumes. Exit status 0 on
success; 2 with one line naming the problem otherwise; 130 when SIGINT or SIGTERM stopped it (a training
stage stops after the step under way and saves its checkpoint there: services/training/stop_signal.py).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time

from services.training.stop_signal import interrupt_text, raise_keyboard_interrupt


def exit_with_parent(parent: int | None = None, poll_s: float = 2.0) -> threading.Thread:
    """Terminate this process (SIGTERM, as the parent's own clean-up would) once its parent — pid `parent`
    (the parent passes its own: one read here could already be an adopter's), else the current parent — is
    gone. Why: a parent killed by a signal that skips its clean-up (SIGTERM, SIGKILL) left its workers
    training on, and a rerun then started a second worker writing the same stage directories (session 24)."""
    parent = os.getppid() if parent is None else parent

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        try:
            print(f"[bench] parent process {parent} is gone: stopping this worker (a rerun resumes it)", flush=True)
        except OSError:  # the log was the parent's pipe
            pass
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=watch, name="n3dmap-bench-parent-watch", daemon=True)
    thread.start()
    return thread


STOPPED_EXIT = 130  # stopped by SIGINT / SIGTERM: nothing failed, a rerun resumes (services.bench.paper reads it)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.bench.seed_worker", description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="the benchmark's REPORT_DIR")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--threads", type=int, required=True, help="torch threads of this process")
    parser.add_argument("--parent-pid", type=int, default=None,
                        help="stop when this process is gone (default: the parent at start-up)")
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")

    exit_with_parent(args.parent_pid)
    # SIGTERM outside a training stage (an evaluation, a data stage) ends the worker as Ctrl-C would, with
    # the same line and exit status; inside one, graceful_stop takes it over and stops between two steps.
    signal.signal(signal.SIGTERM, raise_keyboard_interrupt)
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
    except KeyboardInterrupt as e:  # SIGINT / SIGTERM: a training stage stops between steps, checkpoint saved
        print(f"[bench] seed {args.seed}: stopped ({interrupt_text(e) or 'interrupted'}); a rerun resumes it",
              flush=True)
        return STOPPED_EXIT
    return 0


if __name__ == "__main__":
    sys.exit(main())
