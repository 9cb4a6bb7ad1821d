"""`n3dmap train occupancy`: the occupancy head (and the mapper unless --freeze-features) from depth labels."""

from __future__ import annotations

from services.cli.train import add_task_parser, run_train


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "occupancy", help="occupancy from point (occupied) and ray (free) labels",
        description="Train the occupancy head on maps of --input-views views, labelled by those views and one "
                    "more (class-balanced logistic loss); --freeze-features keeps the mapper fixed.")
    parser.add_argument("--input-views", type=int, default=1, help="views the map is built from (paper: 1)")
    parser.set_defaults(func=lambda args: run_train("occupancy", args, {"input_views": args.input_views}))
