"""The egomotion option `serve` and `stream bridge` share: `--egomotion-fine module|splat|off`, which last,
weightless alignment stage the bundle's egomotion module runs (core/models/egomotion_fine.py).

Why a choice and why the bridge defaults to the splat stage: a module's own stage (point-to-TSDF on a grid 4×
finer than the map's, for modules trained since session 25) is on par with ICP but costs ~2 s per frame at
the small preset on one thread; the splat stage on a 2× finer grid costs ~0.1 s, keeps a 10 Hz stream
going, and its ~0.015 m error is far below what moving-object boxes on 0.5 m voxels notice."""

from __future__ import annotations

import argparse

FINE_CHOICES = ("module", "splat", "off")


def add_egomotion_arguments(parser: argparse.ArgumentParser, *, default: str = "module") -> None:
    parser.add_argument("--egomotion-fine", choices=FINE_CHOICES, default=default,
                        help="egomotion's last, weightless alignment stage: 'module' the bundle module's own (new "
                             "modules: frame 1's points against frame 0's TSDF on a 4x finer grid, on par with "
                             "point-to-plane ICP, ~2 s per frame at small and ~0.3 s at tiny on one thread at load "
                             "~4.5), 'splat' the splat alignment on a 2x finer grid (~0.1 s; ~5x ICP's error), "
                             "'off' none (the learned stages' estimate, ~10x ICP's error). Only for a module that has "
                             f"such a stage. Default: {default}")
    parser.add_argument("--no-egomotion-fine", dest="egomotion_fine", action="store_const", const="off",
                        help="the same as --egomotion-fine off")
