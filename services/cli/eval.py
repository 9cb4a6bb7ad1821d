"""`n3dmap eval KIND ...`: evaluate a bundle (or prediction files) on a dataset and write a report.

Every kind writes REPORT_DIR/report.md and metrics.json, and PNG plots (all but retrieval), through one writer
(`services.reports.Report`). A kind lives in a module listed in `EVAL_KINDS` that exposes
`register(kind_subparsers)`; most build their parser with `add_eval_parser` (the shared options
`--data --bundle --out --max-records --device`) and set `func`. Adding a kind (detection, moving, retrieval, all) is one line here plus its module.
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from typing import Iterator

from services.cli.argtypes import positive_int
from services.cli.paths import check_creatable_dir

# kind -> module with register(kind_subparsers), in `n3dmap eval --help` order.
EVAL_KINDS: dict[str, str] = {
    "egomotion": "services.cli.eval_tasks.egomotion",
    "flow": "services.cli.eval_tasks.flow",
    "occupancy": "services.cli.eval_tasks.occupancy",
    "detection": "services.cli.eval_tasks.detection",
    "moving": "services.cli.eval_tasks.moving",
    "retrieval": "services.cli.eval_tasks.retrieval",
    "all": "services.cli.eval_tasks.all",
}


def add_eval_parser(kinds, name: str, *, help: str, description: str | None = None,
                    needs_bundle: bool = True) -> argparse.ArgumentParser:
    """Add `n3dmap eval NAME` with the shared options; the caller adds its own and sets func."""
    parser = kinds.add_parser(name, help=help, description=description or help)
    parser.add_argument("--data", required=True, metavar="DIR", help="dataset directory (manifest.json + shards)")
    if needs_bundle:
        parser.add_argument("--bundle", required=True, metavar="DIR", help="model bundle to evaluate")
    parser.add_argument("--out", required=True, metavar="REPORT_DIR",
                        help="where report.md, metrics.json and the PNG plots go (created)")
    parser.add_argument("--max-records", type=positive_int, default=None, metavar="N",
                        help="evaluate only the first N records (default: all)")
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default: auto)")
    return parser


def add_rerun_option(parser: argparse.ArgumentParser) -> None:
    """`--rerun FILE.rrd`: record each evaluated item in 3D (services.viz.rerun_eval)."""
    parser.add_argument("--rerun", metavar="FILE.rrd", default=None,
                        help="also write a Rerun recording of every evaluated item in 3D, in ref (open it with "
                             "`rerun FILE.rrd`; needs the viz extra: pip install -e '.[viz]')")


def check_rerun_option(args: argparse.Namespace) -> None:
    """Fail before any slow work when --rerun cannot be honoured (no viz extra, unwritable path)."""
    if getattr(args, "rerun", None) is not None:
        from services.viz.rerun_sdk import check_rrd_path, require_rerun

        require_rerun()
        check_rrd_path(args.rerun)


def open_rerun_option(args: argparse.Namespace, bundle, *, timeline: str, kind: str):
    """The EvalRecorder of --rerun (None without it); close it with services.viz.rerun_eval.close_eval_recorder."""
    if getattr(args, "rerun", None) is None:
        return None
    from services.viz.rerun_eval import open_eval_recorder

    return open_eval_recorder(args.rerun, grid=bundle.preset.grid.to_dict(), timeline=timeline,
                              name=f"n3dmap eval {kind}: {args.bundle} on {args.data}")


def print_rerun_option(args: argparse.Namespace, recorder) -> None:
    """One line naming the recording --rerun wrote, its size and entry count."""
    if recorder is not None:
        from services.cli.data import _human_bytes

        size = _human_bytes(Path(args.rerun).stat().st_size)
        print(f"-> {args.rerun} ({size}, {recorder.entries} entries on timeline '{recorder.timeline}'; "
              f"open it with `rerun {args.rerun}`)")


def iter_records(data_dir: str, max_records: int | None, *, flag: str = "--data") -> Iterator[dict]:
    """Records of the dataset in order, at most `max_records` (DataError names a bad shard; CliError names
    `flag`, the option that gave the directory)."""
    from core.data.shards import ShardDataset
    from services.cli.main import CliError

    if not Path(data_dir).is_dir():
        raise CliError(f"{flag} {data_dir}: not a directory")
    if max_records is not None and max_records < 1:
        raise CliError(f"--max-records must be at least 1, got {max_records}")
    dataset = ShardDataset(data_dir)
    n = len(dataset) if max_records is None else min(max_records, len(dataset))
    if n == 0:
        raise CliError(f"{flag} {data_dir}: the dataset holds no records")
    for i in range(n):
        yield dataset[i]


def load_bundle_for_eval(path: str, device, needed: tuple[str, ...], *, data_dir: str | None = None):
    """Load the bundle and check it holds the modules an evaluation needs and, given `data_dir`, that
    the dataset was made for the bundle's preset (its grid and cameras; as `n3dmap train` checks)."""
    from core.bundle import load_bundle
    from core.errors import BundleError

    data_preset = _data_preset(data_dir) if data_dir is not None else None  # a bad dataset fails first
    bundle = load_bundle(path, device)
    missing = [m for m in needed if m not in bundle.modules]
    if missing:
        raise BundleError(f"--bundle {path}: lacks module(s) {missing} (it holds {sorted(bundle.modules)})")
    if data_dir is not None:
        _check_preset(data_preset, data_dir, bundle, bundle_path=path, flag="--data")
    return bundle


def _data_preset(data_dir: str) -> str | None:
    from core.data.shards import load_manifest

    return load_manifest(data_dir).get("preset")


def check_data_preset(data_dir: str, bundle, *, bundle_path: str, flag: str = "--data") -> None:
    """DataError naming `flag` when the dataset at `data_dir` was made for another preset than the bundle's."""
    _check_preset(_data_preset(data_dir), data_dir, bundle, bundle_path=bundle_path, flag=flag)


def _check_preset(data_preset: str | None, data_dir: str, bundle, *, bundle_path: str, flag: str) -> None:
    from core.errors import DataError

    if data_preset is not None and data_preset != bundle.preset.name:
        raise DataError(f"{flag} {data_dir} was made with preset {data_preset!r}, but --bundle {bundle_path} is a "
                        f"{bundle.preset.name!r} bundle")


def register(subparsers) -> None:
    parser = subparsers.add_parser("eval", help="evaluate a bundle on a dataset and write a report",
                                   description="Evaluate and write REPORT_DIR/report.md, metrics.json and plots.")
    kinds = parser.add_subparsers(dest="eval_kind", metavar="KIND", required=True)
    for module_name in EVAL_KINDS.values():
        importlib.import_module(module_name).register(kinds)
    for kind_parser in kinds.choices.values():   # every kind: REPORT_DIR checked before the evaluation runs
        kind_parser.set_defaults(func=_checking_report_dir(kind_parser.get_default("func")))


def _checking_report_dir(run):
    """`run` after checking that --out can be created: a report is written at the end of the work."""
    def checked(args: argparse.Namespace):
        check_creatable_dir(args.out, "--out")
        return run(args)
    return checked
