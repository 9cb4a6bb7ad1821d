"""`n3dmap train occupancy`: the occupancy head (and the mapper unless --freeze-features) from depth labels."""

from __future__ import annotations

import json
from pathlib import Path

from services.cli.argtypes import positive_int
from services.cli.train import add_task_parser, run_train
from services.training.config import TrainConfigError


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "occupancy", help="occupancy from point (occupied) and ray (free) labels",
        description="Train the occupancy head on maps of --input-views views, labelled by those views and one "
                    "more (class-balanced logistic loss); --freeze-features keeps the mapper fixed.")
    parser.add_argument("--input-views", type=positive_int, default=1, help="views the map is built from (paper: 1)")
    parser.set_defaults(func=_run)


def _run(args) -> int:
    views = _dataset_views(args.data)
    if views is not None and args.input_views > views:
        raise TrainConfigError(f"--input-views {args.input_views}: the records of {args.data} have {views} views")
    return run_train("occupancy", args, {"input_views": args.input_views})


def _dataset_views(data_dir: str) -> int | None:
    """The fewest views of a record in the dataset's manifest (None when unreadable here, e.g. a path
    on a cluster; the run reports a missing dataset itself)."""
    try:
        return int(json.loads((Path(data_dir) / "manifest.json").read_text())["dims"]["V"][0])
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None
