"""`n3dmap train flow`: the 3D imagination flow module (synthetic rigid + warp + smooth losses)."""

from __future__ import annotations

from services.cli.argtypes import non_negative_float, non_negative_int
from services.cli.errors import CliError
from services.cli.train import add_task_parser, run_train


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "flow", help="3D imagination flow (PWC-style) between egomotion-stabilised frames",
        description="Train the 3D flow module between egomotion-stabilised frames: supervised synthetic rigid "
                    "motions (large/small/zero thirds) + a warp loss on real pairs + smoothness. It compares "
                    "the fused occupancy+RGB input volumes by default (--inputs volume; small feature maps "
                    "were measured not to carry object motion) or, as the paper, the mapper's feature maps "
                    "(--inputs features, which needs a pretrained mapper from --init). The mapper from --init "
                    "is kept fixed; its occupancy head, if any, gates the flow at test time. The default "
                    "learning rate is the preset's flow rate (the paper's 1e-4 at the paper preset).")
    parser.add_argument("--inputs", choices=("volume", "features"), default="volume",
                        help="what the module compares: input volumes (default) or mapper features")
    parser.add_argument("--warp-weight", type=non_negative_float, default=1.0,
                        help="weight of the real pair's 3D feature-constancy loss over occupied voxels (default 1)")
    parser.add_argument("--smooth-weight", type=non_negative_float, default=0.05,
                        help="weight of the real pair's flow smoothness loss, mean |grad flow| (default 0.05)")
    parser.add_argument("--radius", type=non_negative_int, nargs=3, default=None, metavar=("RX", "RY", "RZ"),
                        help="cost-volume window in voxels (x, y, z) at every level (default 1 1 1; 2 1 2 "
                             "measured better over matching-trained features, docs/findings.md)")
    parser.add_argument("--refine-radius", type=non_negative_int, nargs=3, default=None, metavar=("RX", "RY", "RZ"),
                        help="window of the last, full-grid correlator step (default 3 1 3: the task's)")
    parser.add_argument("--cost-channels", type=non_negative_int, default=None, metavar="K",
                        help="squeeze the window's costs to K channels (a learned 1x1x1 conv) before each "
                             "decoder, so a wide --radius costs little (default: the task's)")
    parser.add_argument("--refine-aggregate", type=non_negative_int, nargs=3, default=None,
                        metavar=("AX", "AY", "AZ"),
                        help="average the full-grid step's costs over a box of +-AX, AY, AZ voxels before its "
                             "soft-argmax (cost aggregation; default 1 1 1: the task's)")
    parser.add_argument("--reproject-fraction", type=float, default=None, metavar="P",
                        help="share of the synthetic rigid steps whose moved input is the frame re-unprojected with "
                             "the motion (large, small, and a jitter at the egomotion module's error scale) "
                             "instead of resampled, so that a slightly wrong stabilising pose is not read as "
                             "motion (default 0; docs/findings.md, 'How this report\'s verdicts moved')")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    if args.inputs == "features" and not args.init:
        # A randomly initialised, frozen mapper gives features that carry nothing to match.
        raise CliError("--inputs features compares the mapper's feature maps and needs a pretrained mapper: "
                       "pass --init BUNDLE (e.g. RUN_DIR/bundle of `n3dmap train pretrain`)")
    options = {"inputs": args.inputs, "warp_weight": args.warp_weight, "smooth_weight": args.smooth_weight}
    if args.radius is not None:
        options["radius"] = list(args.radius)
    if args.refine_radius is not None:
        options["refine_radius"] = list(args.refine_radius)
    if args.cost_channels is not None:
        options["cost_channels"] = args.cost_channels
    if args.refine_aggregate is not None:
        options["refine_aggregate"] = list(args.refine_aggregate)
    if args.reproject_fraction is not None:
        if not 0.0 <= args.reproject_fraction <= 1.0:
            raise CliError(f"--reproject-fraction must lie in [0, 1], got {args.reproject_fraction}")
        options["reproject_fraction"] = args.reproject_fraction
    return run_train("flow", args, options)
