"""`n3dmap train flow`: 3D imagination flow over frozen mapper features (synthetic rigid + warp + smooth)."""

from __future__ import annotations

from services.cli.train import add_task_parser, run_train


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "flow", help="3D imagination flow (PWC-style) over frozen features",
        description="Train the 3D flow module between egomotion-stabilised maps: supervised synthetic rigid "
                    "motions (large/small/zero thirds) + feature-warp loss on real pairs + smoothness. The "
                    "mapper (from --init) is always kept fixed. The paper used a learning rate of 1e-4 for "
                    "flow (--lr 1e-4).")
    parser.add_argument("--warp-weight", type=float, default=1.0)
    parser.add_argument("--smooth-weight", type=float, default=0.05)
    parser.set_defaults(func=lambda args: run_train("flow", args, {
        "warp_weight": args.warp_weight, "smooth_weight": args.smooth_weight}))
