"""`n3dmap train pretrain`: view-predictive pretraining of the 3D mapper (contrastive or regression)."""

from __future__ import annotations

from services.cli.argtypes import non_negative_float, non_negative_int
from services.cli.errors import CliError
from services.cli.train import add_task_parser, run_train

OBJECTIVES = ("contrastive", "regression")


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "pretrain", help="view-predictive pretraining (contrastive or RGB regression)",
        description="Pretrain the 3D feature mapper by predicting a held-out view: the paper's 2D+3D "
                    "view-contrastive objective, or the RGB view-regression baseline.")
    parser.add_argument("--objective", choices=OBJECTIVES, default="contrastive",
                        help="view-contrastive (paper) or RGB view regression (baseline)")
    parser.add_argument("--match-weight", type=non_negative_float, default=0.0,
                        help="weight of the local matching term (0, the default: off; the paper has none): "
                             "an object-sized block of one view's input moves and each moved voxel's feature "
                             "must find itself again among its new place's neighbours, so that 3D flow over "
                             "the maps can follow objects (docs/findings.md, flow over features)")
    parser.add_argument("--local-negatives", type=non_negative_float, default=0.0, metavar="W",
                        help="weight of local negatives in the 3D contrastive loss (0, the default: off, the "
                             "paper's batch-wide negatives only): each sampled voxel's prediction must also differ "
                             "from the observed feature of a random neighbour (contrastive only; README: Training)")
    parser.add_argument("--local-negative-radius", type=non_negative_int, default=2, metavar="R",
                        help="neighbours of --local-negatives within ±R voxels per axis (default 2)")
    parser.add_argument("--shift-positives", type=non_negative_int, default=0, metavar="N",
                        help="3D contrastive positives across grid placements (0, the default: off, the paper's "
                             "aligned maps): the target view is lifted into a grid moved by a random whole-voxel "
                             "offset within ±N per axis and its features moved back before the loss, so that "
                             "features must follow content moved by less than the encoder's stride (contrastive "
                             "only; README: Training)")
    parser.add_argument("--occupancy-weight", type=non_negative_float, default=None, metavar="W",
                        help="weight of the occupancy loss (default 1); 3 measured to keep the occupancy head "
                             "with --match-weight 1 (docs/findings.md, occupancy)")
    parser.add_argument("--encoder-full-res", type=non_negative_int, default=0, metavar="N",
                        help="channels of the 3D encoder's full-resolution branch (0, the default: the paper's "
                             "layers); with --match-weight it makes features follow objects moved 1-3 voxels "
                             "(docs/findings.md). Later tasks started with --init take it from the bundle")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    options = {"objective": args.objective}
    if args.match_weight > 0:  # recorded only when used: the default run's config stays the paper's
        options["coeff_match"] = args.match_weight
    if args.local_negatives > 0:
        if args.objective != "contrastive":
            raise CliError("--local-negatives needs --objective contrastive (view regression has no negatives)")
        if args.local_negative_radius < 1:
            raise CliError(f"--local-negative-radius must be >= 1 voxel, got {args.local_negative_radius}")
        options["coeff_local_negatives"] = args.local_negatives
        options["local_negative_radius"] = args.local_negative_radius
    if args.shift_positives > 0:
        if args.objective != "contrastive":
            raise CliError("--shift-positives needs --objective contrastive (view regression has no 3D positives)")
        options["shift_positives"] = args.shift_positives
    if args.occupancy_weight is not None:
        options["coeff_occ"] = args.occupancy_weight
    if args.encoder_full_res > 0:
        options["encoder_full_res"] = args.encoder_full_res
    return run_train("pretrain", args, options)
