"""`n3dmap train pretrain`: view-predictive pretraining of the 3D mapper (contrastive or regression)."""

from __future__ import annotations

from services.cli.train import add_task_parser, run_train

OBJECTIVES = ("contrastive", "regression")


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "pretrain", help="view-predictive pretraining (contrastive or RGB regression)",
        description="Pretrain the 3D feature mapper by predicting a held-out view: the paper's 2D+3D "
                    "view-contrastive objective, or the RGB view-regression baseline.")
    parser.add_argument("--objective", choices=OBJECTIVES, default="contrastive",
                        help="view-contrastive (paper) or RGB view regression (baseline)")
    parser.set_defaults(func=lambda args: run_train("pretrain", args, {"objective": args.objective}))
