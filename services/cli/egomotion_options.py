"""The egomotion option `serve` and `stream bridge` share: `--egomotion-fine module|splat|off`, which last,
weightless alignment stage the bundle's egomotion module runs (core/models/egomotion_fine.py).

Why a choice and why both default to the splat stage: a module's own stage (point-to-TSDF on a grid 4× finer
than the map's, for modules trained since session 25) is on par with ICP but costs ~1.8 s per pair at the small
preset on one thread — a micro-batch of 8 would take half a request's 30 s deadline, and a 10 Hz stream could
not keep up; the splat stage on a 2× finer grid costs ~0.1 s per pair for ~0.015 m error (held-out pairs)."""

from __future__ import annotations

import argparse

FINE_CHOICES = ("module", "splat", "off")


def add_egomotion_arguments(parser: argparse.ArgumentParser, *, default: str = "splat") -> None:
    parser.add_argument("--egomotion-fine", choices=FINE_CHOICES, default=default,
                        help="egomotion's last, weightless alignment stage: 'module' the bundle module's own (new "
                             "modules: frame 1's points against frame 0's TSDF on a 4x finer grid, on par with "
                             "point-to-plane ICP, ~1.8 s per pair at small and ~0.3 s at tiny on one thread at load "
                             "~4.5), 'splat' the default splat stage (a 2x finer grid, 3 Gauss-Newton steps; ~0.1 s per pair; "
                             "~5x ICP's error on held-out pairs), "
                             "'off' none (the learned stages' estimate, ~10x ICP's error). Only for a module that has "
                             f"such a stage. Default: {default}")
    parser.add_argument("--no-egomotion-fine", dest="egomotion_fine", action="store_const", const="off",
                        help="the same as --egomotion-fine off")
