"""The egomotion option `serve` and `stream bridge` share: `--egomotion-fine / --no-egomotion-fine`, whether
the bundle's egomotion module runs its last, finer alignment stage (core/models/egomotion_fine.py)."""

from __future__ import annotations

import argparse


def add_egomotion_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--egomotion-fine", action=argparse.BooleanOptionalAction, default=True,
                        help="egomotion: run the module's last alignment stage on a 2x finer grid (default; docs/findings.md, "
                             "'Egomotion is on par with ICP': 0.5x ICP's rotation error on held-out pairs instead of 1.2x). "
                             "--no-egomotion-fine skips it: ~90 ms less per pair at the small preset on one "
                             "thread, which a stream at 10 Hz may need")
