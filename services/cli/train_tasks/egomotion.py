"""`n3dmap train egomotion`: supervised coarse-to-fine 6-DoF egomotion from record poses."""

from __future__ import annotations

import argparse

from services.cli.argtypes import non_negative_float
from services.cli.train import add_task_parser, run_train


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "egomotion", help="supervised 6-DoF egomotion (ref0_T_ref1 from record poses)",
        description="Train the egomotion module (its own 3D encoder, candidate rotations × 3D cost volumes, "
                    "an MLP per scale, inverse-compositional) on consecutive frames; random yaw-heavy "
                    "perturbations of the second frame's map frame augment the pairs.")
    parser.add_argument("--no-augment", action="store_true", help="train on the recorded motion only")
    parser.add_argument("--augment-deg", type=non_negative_float, default=6.0,
                        help="largest yaw perturbation (degrees)")
    parser.add_argument("--augment-m", type=non_negative_float, default=1.0,
                        help="largest x/z perturbation (metres)")
    parser.add_argument("--occupancy", choices=("binary", "splat"), default=None,
                        help="occupancy channel of the input volumes (default: the task's)")
    parser.add_argument("--refine", action=argparse.BooleanOptionalAction, default=None,
                        help="add the sub-voxel Gauss-Newton stage (default: the task's)")

    def options(args) -> dict:
        opts = {"augment": not args.no_augment, "augment_deg": args.augment_deg, "augment_m": args.augment_m}
        if args.occupancy is not None:
            opts["input_occupancy"] = args.occupancy
        if args.refine is not None:
            opts["refine"] = args.refine
        return opts

    parser.set_defaults(func=lambda args: run_train("egomotion", args, options(args)))
