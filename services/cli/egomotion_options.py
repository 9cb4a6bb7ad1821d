"""The egomotion option `serve` and `stream bridge` share: `--egomotion-fine / --no-egomotion-fine`, whether
the bundle's egomotion module runs its last, finer alignment stage (core/models/egomotion_fine.py)."""

from __future__ import annotations

import argparse


def add_egomotion_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--egomotion-fine", action=argparse.BooleanOptionalAction, default=True,
                        help="egomotion: run the module's last, weightless alignment stage (default): new modules align "
                             "frame 1's points with frame 0's TSDF on a 4x finer grid (docs/findings.md, 'Egomotion': on "
                             "par with point-to-plane ICP on the small report's moving test pairs, ~5x less error than the "
                             "learned stages alone); it costs ~2 s per frame at the small preset and ~0.3 s at tiny on one thread "
                             "(measured at load ~4.5 on 2 cores). --no-egomotion-fine skips it, which a "
                             "stream at 10 Hz needs")
