"""`n3dmap train detector`: the Faster-RCNN-style 3D detector on the latent map (paper §5.1).

`--labels N` gives box labels to the first N records of the dataset (by index) only; the others
contribute no detection loss. The detector has no other loss, so a record without labels adds
nothing to training: the command trains on RUN_DIR/labelled_data, a copy of the first N records
(same keys), rather than spending steps on masked records. (In-process callers can instead build the
task with labels=N and give the batch `record_index`; see core/tasks/detector.py.)
Features are frozen by default (`--freeze-features`, the paper's protocol after pretraining);
`--finetune` trains the mapper too. `--init BUNDLE` starts from a pretrained mapper; without it the
mapper is randomly initialised (the paper's baseline).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.data.shards import KEY_FIELD
from core.errors import DataError
from services.cli.main import CliError
from services.cli.train import add_task_parser, run_train


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
    parser.add_argument("--finetune", action="store_true",
                        help="train the mapper's features together with the detector "
                             "(default: --freeze-features)")
    # Default: frozen features. None tells "not given" from an explicit --freeze-features.
    parser.set_defaults(freeze_features=None, func=_run)


LABELLED_SUBDIR = "labelled_data"


def _run(args) -> int:
    if args.finetune and args.freeze_features:
        raise CliError("train detector: --freeze-features and --finetune exclude each other")
    args.freeze_features = not args.finetune
    if args.labels is not None and not args.address:  # a submitted job subsets on the cluster
        args.data = str(labelled_subset(Path(args.data), Path(args.run_dir), args.labels))
    return run_train("detector", args, {"freeze_features": args.freeze_features})


def labelled_subset(data_dir: Path, run_dir: Path, count: int) -> Path:
    """RUN_DIR/labelled_data: the first `count` records of `data_dir` (written once; a rerun reuses it
    and refuses a different --labels, since the run's checkpoints were trained on that subset)."""
    from core.data.shards import ShardDataset, load_manifest, write_dataset

    if count < 1:
        raise CliError("train detector: --labels must be at least 1 (a detector needs labelled records)")
    if not data_dir.is_dir():
        raise DataError(f"--data {data_dir}: no such dataset directory")
    out = run_dir / LABELLED_SUBDIR
    source = ShardDataset(data_dir)
    wanted = min(count, len(source))
    if (out / "manifest.json").is_file():
        generator = load_manifest(out).get("generator") or {}
        have = (generator.get("label_subset_of"), generator.get("label_records"))
        if have != (str(data_dir.resolve()), wanted):
            raise CliError(f"train detector: run dir {run_dir} was trained on the first {have[1]} records of "
                           f"{have[0]}; use a new --run-dir for --labels {count} of {data_dir}")
        return out
    if count > len(source):
        print(f"detector: --labels {count} exceeds the dataset's {len(source)} records; using all of them")
    manifest = source.manifest
    generator = dict(manifest.get("generator") or {}, label_subset_of=str(data_dir.resolve()),
                     label_records=wanted)
    records = ({**source[i], KEY_FIELD: source.key(i)} for i in range(wanted))
    write_dataset(out, records, split=manifest.get("split", "train"), preset_name=manifest.get("preset"),
                  grid=manifest.get("grid"), generator=generator, seed=manifest.get("seed"), overwrite=True)
    print(f"detector: box labels from the first {wanted} records of {data_dir} ({out})")
    return out
