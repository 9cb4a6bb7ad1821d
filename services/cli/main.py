"""The `n3dmap` console command: one argparse tree, one subcommand module per area.

Each area module exposes `register(subparsers)`, adding its parser(s) with `set_defaults(func=...)`.
Only the area being run is imported (torch, Ray, matplotlib and gRPC make a full import cost seconds);
the others appear in `n3dmap --help` through their one-line summaries below.
Errors the user can fix (N3dmapError, CliError, OSError: bad paths, taken ports) print one line naming what is wrong
and exit 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from services.cli.errors import CliError  # noqa: F401  (re-exported: area modules raise it)

# Area modules, in the order they appear in `n3dmap --help`, with their summaries.
AREAS: dict[str, str] = {
    "data": "generate, import, inspect and preview datasets",
    "train": "train a task (pretrain, egomotion, occupancy, flow, detector) on Ray Train",
    "jobs": "list / inspect / stop training jobs on a Ray cluster",
    "bundle": "inspect model bundles",
    "eval": "evaluate a bundle on a dataset and write a report",
    "bench": "benchmarks that reproduce the paper's tables on the synthetic world",
    "serve": "serve a model bundle over REST (FastAPI) and gRPC",
    "stream": "live RGB-D over zenoh: bridge, simulated camera, listener, 3D viewer",
}


def build_parser(argv: list[str] | None = None, *, full: bool = False) -> argparse.ArgumentParser:
    """The parser; with `full=True` every area registers its real subcommands (tests use this to
    check manifests and docs against the real options), else only the one named in `argv`."""
    parser = argparse.ArgumentParser(
        prog="n3dmap",
        description="n3dmap: learn 3D feature maps from RGB-D video by view-contrastive prediction; "
                    "train on Ray, serve over REST/gRPC, stream over zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"n3dmap {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    wanted = next((a for a in (argv or []) if not a.startswith("-")), None)
    for area, summary in AREAS.items():
        if full or area == wanted:
            importlib.import_module(f"services.cli.{area}").register(sub)
        else:
            sub.add_parser(area, help=summary, add_help=False)  # a placeholder: parsing it needs `wanted`
    return parser


def _version() -> str:
    from core import __version__
    return __version__


def _one_line(error: BaseException) -> str:
    """The error's message on one line (some libraries' messages span several)."""
    return " ".join(str(error).split())


def main(argv: list[str] | None = None) -> int:
    from core.errors import N3dmapError

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if args.command != "serve":  # the server's requests of every size would fragment a never-trimmed heap
        from services.malloc import keep_heap

        keep_heap()  # glibc: large tensors reuse the heap instead of fresh, page-faulted mmaps (services/malloc.py)
    try:
        result = args.func(args)
    except BrokenPipeError:  # `n3dmap ... | head`: the reader left (an OSError, so caught first)
        sys.stderr.close()
        return 0
    except (N3dmapError, CliError, OSError) as e:
        # OSError: a path the user gave that cannot be made or written (a file where a folder must be,
        # a read-only or full disk, a port or endpoint that cannot be reached) — their fix, not a bug.
        print(f"n3dmap {args.command}: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        from services.training.stop_signal import interrupt_text

        said = " ".join(interrupt_text(e).split())
        print(f"n3dmap {args.command}: interrupted" + (f": {said}" if said else ""), file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
