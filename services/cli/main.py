"""The `n3dmap` console command: one argparse tree, one subcommand module per area.

Each area module exposes `register(subparsers)`, adding its parser(s) with `set_defaults(func=...)`.
Errors the user can fix (N3dmapError, CliError, missing files) print one line naming what is wrong
and exit 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Area modules, in the order they appear in `n3dmap --help`. A module that is absent (not yet
# built) is skipped, so the CLI never fails to start because one area is missing.
AREAS = ("data", "train", "jobs", "bundle", "eval", "bench", "serve", "stream")


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="n3dmap",
        description="n3dmap: learn 3D feature maps from RGB-D video by view-contrastive prediction; "
                    "train on Ray, serve over REST/gRPC, stream over zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"n3dmap {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for area in AREAS:
        try:
            module = importlib.import_module(f"services.cli.{area}")
        except ModuleNotFoundError as e:
            if e.name == f"services.cli.{area}":
                continue
            raise
        module.register(sub)
    return parser


def _version() -> str:
    from core import __version__
    return __version__


def main(argv: list[str] | None = None) -> int:
    from core.errors import N3dmapError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except (N3dmapError, CliError, FileNotFoundError, NotADirectoryError, PermissionError) as e:
        print(f"n3dmap {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"n3dmap {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
