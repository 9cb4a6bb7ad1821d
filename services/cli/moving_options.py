"""The moving-object post-processing options `serve` and `stream bridge` share: `--size-prior L W H` and
`--min-object-speed M_S` -> one core.pipeline.moving_boxes.MovingObjectsConfig. Building the parser
imports no torch (the defaults come from services.cli.argtypes)."""

from __future__ import annotations

import argparse

from services.cli.argtypes import DEFAULT_MIN_OBJECT_SPEED, non_negative_float, positive_float


def add_moving_object_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--size-prior", type=positive_float, nargs=3, default=None, metavar=("L", "W", "H"),
                        help="moving objects: amodal boxes of this object size in metres (length, width, height): "
                             "oversized components are split or dropped, partial ones completed, footprints capped "
                             "at 1.25 × it (default: visible boxes); `n3dmap eval moving` estimates it without "
                             "labels and prints it in its report")
    parser.add_argument("--min-object-speed", type=non_negative_float, default=DEFAULT_MIN_OBJECT_SPEED,
                        metavar="M_S", help="moving objects: m/s under which a component of moving voxels is no "
                                            "moving object (default %(default)s; README \"Which voxels move\")")


def moving_objects_config(args: argparse.Namespace):
    """The MovingObjectsConfig of the parsed options (ValueError naming a value out of range)."""
    from core.moving.amodal import SizePrior
    from core.pipeline.moving_boxes import MovingObjectsConfig

    prior = None if args.size_prior is None else SizePrior.from_size(*args.size_prior)
    return MovingObjectsConfig(size_prior=prior, min_object_speed=args.min_object_speed)
