"""`n3dmap train detector`: the Faster-RCNN-style 3D detector on the latent map (paper §5.1).

`--labels N` gives box labels to the first N records of the dataset (by index) only, `--labels-from I`
to records I … I+N−1 instead (another label draw, as `bench paper --label-draws` trains); the others
contribute no detection loss. The detector has no other loss, so a record without labels adds
nothing to training: the command trains on RUN_DIR/labelled_data, a copy of the first N records
(same keys; services.training.label_subset), rather than spending steps on masked records. (In-process callers can instead build the
task with labels=N and give the batch `record_index`; see core/tasks/detector.py.)
Features are frozen by default (`--freeze-features`, the paper's protocol after pretraining);
`--finetune` trains the mapper too. `--init BUNDLE` starts from a pretrained mapper; without it the
mapper is randomly initialised (the paper's baseline).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.main import CliError
from services.cli.train import add_task_parser, run_train
from services.training.label_subset import labelled_subset


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number of records (an integer ≥ 0), got {text!r}")
    return value


def register(tasks) -> None:
    parser = add_task_parser(
        tasks, "detector", help="3D object detector on the latent map (axis-aligned boxes + objectness)",
        description="Train the Faster-RCNN-style 3D detector on the latent map with box labels from the "
                    "first N records; the mapper comes from --init BUNDLE (pretrained) or is randomly "
                    "initialised, and stays frozen unless --finetune.")
    parser.add_argument("--labels", type=_non_negative_int, default=None, metavar="N",
                        help="box labels from the first N records of the dataset only (default: all)")
    parser.add_argument("--labels-from", type=_non_negative_int, default=0, metavar="I",
                        help="with --labels N: box labels from records I to I+N-1 instead (default 0)")
    parser.add_argument("--finetune", action="store_true",
                        help="train the mapper's features together with the detector "
                             "(default: --freeze-features)")
    # Default: frozen features. None tells "not given" from an explicit --freeze-features.
    parser.set_defaults(freeze_features=None, func=_run)


def _run(args) -> int:
    if args.finetune and args.freeze_features:
        raise CliError("train detector: --freeze-features and --finetune exclude each other")
    args.freeze_features = not args.finetune
    if args.labels_from and args.labels is None:
        raise CliError("train detector: --labels-from I needs --labels N (how many records from I get labels)")
    if args.labels is not None and not args.address:  # a submitted job subsets on the cluster
        args.data = str(labelled_subset(Path(args.data), Path(args.run_dir), args.labels, first=args.labels_from,
                                        log=print))
    return run_train("detector", args, {"freeze_features": args.freeze_features})
