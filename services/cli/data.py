"""`n3dmap data`: generate, import, inspect, verify and preview sharded datasets.

    n3dmap data generate --out DIR --preset tiny --episodes 64 --seed 0 [--views V] [--frames T]
                         [--split train|val] [--moving-ego on|off|mixed] [--sparse-depth]
                         [--noise SIGMA] [--exposure-jitter S] [--white-balance-jitter S]
                         [--pixel-noise S] [--texture-scale LO HI] [--shard-mb MB] [--overwrite] [--jobs N]
    n3dmap data info DIR [--verify] [--json]
    n3dmap data preview DIR [--out FILE.png] [--rerun FILE.rrd [--points]] [--index I]
    n3dmap data import authors-npz|kitti|tum SRC --out DIR [...]

Seeds: record i of `generate --seed S` is `core.synthetic.generate_record(preset, seed=S*100003 + i)`
(core.data.seeds), so a record can be rebuilt alone and datasets made with different S never share
a record for S*100003 + i distinct (fewer than 100003 records per dataset). `--moving-ego mixed` moves the ego in
the odd-indexed records. `--jobs N` renders in N processes of one torch thread each (render_pool.py);
the records and their bytes do not depend on N.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

# Errors are raised as core.errors types (not services.cli.main.CliError): under
# `python -m services.cli.main` that module is __main__, and its CliError would be a different class.
from core.errors import DataError, N3dmapError
from core.data.seeds import SEED_STRIDE, episode_seed
from services.cli.argtypes import non_negative_float, non_negative_int, positive_float, positive_int
from services.cli.paths import check_creatable_dir


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "data", help="generate, import, inspect and preview datasets",
        description="Datasets are directories of manifest.json + tar shards of npz records "
                    "(docs/data.md#shards-and-manifest).")
    sub = parser.add_subparsers(dest="data_command", metavar="SUBCOMMAND", required=True)

    g = sub.add_parser("generate", help="render a synthetic dataset (built-in world, no downloads)",
                       description="Render records of the built-in synthetic world into shards. Record i "
                                   f"uses seed = SEED*{SEED_STRIDE} + i.")
    g.add_argument("--out", required=True, type=Path, help="dataset directory to create")
    g.add_argument("--preset", required=True, choices=["tiny", "small", "paper"])
    g.add_argument("--episodes", required=True, type=positive_int, help="number of records")
    g.add_argument("--seed", type=non_negative_int, default=0, help="dataset seed S (record i uses S*100003+i)")
    g.add_argument("--views", type=positive_int, default=None, help="views per record (default: preset)")
    g.add_argument("--frames", type=positive_int, default=None, help="time steps per record (default: preset)")
    g.add_argument("--split", choices=["train", "val"], default="train")
    g.add_argument("--moving-ego", choices=["on", "off", "mixed"], default="off",
                   help="whether the ego rig moves (mixed: odd-indexed records)")
    g.add_argument("--sparse-depth", action="store_true", help="LiDAR-like sparse depth")
    g.add_argument("--noise", type=non_negative_float, default=0.0, help="depth noise sigma, metres")
    g.add_argument("--exposure-jitter", type=non_negative_float, default=0.0, metavar="S",
                   help="std of each image's log gain (auto-exposure); default 0: off")
    g.add_argument("--white-balance-jitter", type=non_negative_float, default=0.0, metavar="S",
                   help="std of each image's per-channel log gain (auto white balance); default 0: off")
    g.add_argument("--pixel-noise", type=non_negative_float, default=0.0, metavar="S",
                   help="per-pixel colour noise std, in [0, 1] colour units; default 0: off")
    g.add_argument("--texture-scale", type=positive_float, nargs=2, default=None, metavar=("LO", "HI"),
                   help="pattern cell sizes (metres) of the objects' textures, drawn uniformly per object "
                        "(default: the preset's, at least one voxel)")
    g.add_argument("--shard-mb", type=positive_float, default=256.0, help="target shard size in MiB")
    g.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")
    g.add_argument("--jobs", type=positive_int, default=None,
                   help="render processes, one torch thread each (default: min(CPUs, 4), or 1 for a "
                        "job of a few seconds; 1: in this process); the output is the same for any N")
    g.set_defaults(func=cmd_generate)

    i = sub.add_parser("info", help="print a dataset's manifest summary (and verify it)")
    i.add_argument("dir", type=Path)
    i.add_argument("--verify", action="store_true", help="check shard sha256 and decode every record")
    i.add_argument("--json", action="store_true", help="print the manifest (without key lists) as JSON")
    i.set_defaults(func=cmd_info)

    p = sub.add_parser("preview", help="write a PNG contact sheet of one record, or a Rerun recording of it",
                       description="Preview one record: a PNG contact sheet (--out) and/or a Rerun recording "
                                   "(--rerun; open it with `rerun FILE.rrd`) of its cameras, RGB-D and "
                                   "ground-truth boxes in 3D over its time steps.")
    p.add_argument("dir", type=Path)
    p.add_argument("--out", type=Path, default=None, help="PNG file to write")
    p.add_argument("--rerun", type=Path, default=None, metavar="FILE.rrd",
                   help="Rerun recording to write (needs the viz extra: pip install -e '.[viz]')")
    p.add_argument("--points", action="store_true",
                   help="with --rerun: log each view's depth as a point cloud instead of a DepthImage")
    p.add_argument("--index", type=int, default=0, help="record index (negative counts from the end)")
    p.set_defaults(func=cmd_preview)

    imp = sub.add_parser("import", help="convert an external dataset into shards")
    isub = imp.add_subparsers(dest="import_format", metavar="FORMAT", required=True)

    a = isub.add_parser("authors-npz", help="the authors' npz files (one file = one record, T=1, V=S)")
    a.add_argument("src", type=Path, help="an .npz file or a directory of them")
    _import_common(a)
    a.set_defaults(func=cmd_import_authors)

    k = isub.add_parser("kitti", help="KITTI object (training/{image_2,velodyne,calib,label_2}, ImageSets)")
    k.add_argument("src", type=Path, help="KITTI object root (holding training/ and ImageSets/)")
    k.add_argument("--resize", type=positive_int, nargs=2, metavar=("H", "W"), default=None,
                   help="resample images (and render depth) at H×W so that all records share one size")
    _import_common(k)
    k.set_defaults(func=cmd_import_kitti)

    t = isub.add_parser("tum", help="a TUM RGB-D sequence (rgb.txt, depth.txt, groundtruth.txt)")
    t.add_argument("src", type=Path, help="sequence directory")
    t.add_argument("--frames", type=positive_int, default=2, help="time steps T per record")
    t.add_argument("--frame-step", type=positive_int, default=1, help="take every k-th associated frame")
    t.add_argument("--stride", type=positive_int, default=None,
                   help="frames between record starts (default: T, non-overlapping)")
    t.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"), default=None,
                   help="pinhole intrinsics (default: 525 525 319.5 239.5, the camera of every TUM sequence's "
                        "registered depth images, as the dataset's calibration page says, for 640×480 frames; "
                        "give the images' own for other sizes)")
    t.add_argument("--max-dt", type=positive_float, default=0.02,
                   help="largest rgb/depth/pose timestamp gap, seconds")
    _import_common(t)
    t.set_defaults(func=cmd_import_tum)


def _import_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, type=Path, help="dataset directory to create")
    p.add_argument("--split", choices=["train", "val"], default="train")
    p.add_argument("--preset", choices=["tiny", "small", "paper"], default="paper",
                   help="the map grid recorded in the manifest (default: paper)")
    p.add_argument("--limit", type=positive_int, default=None, help="import at most this many records")
    p.add_argument("--shard-mb", type=positive_float, default=256.0, help="target shard size in MiB")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")


# One record's images are rendered, checked and written whole (uint8 RGB + float32 depth per pixel); a record
# over this would exhaust the memory of a typical machine — the kernel then kills the process without a word.
# The presets' records take 0.3–3 MB.
RECORD_BYTES_PER_PIXEL = 3 + 4
MAX_RECORD_BYTES = 1 << 30


def _shard_bytes(mb: float) -> int:
    return max(1, int(mb * (1 << 20)))


class _Progress:
    """A stderr progress bar (tqdm), opened at the first record so that errors found before any work
    (a bad path, a non-empty --out) print as one line with no bar; closed before any error is printed."""

    def __init__(self, total: int | None, desc: str) -> None:
        self._total, self._desc, self._bar = total, desc, None

    def __call__(self, count: int, key: str) -> None:
        if self._bar is None:
            from tqdm import tqdm
            self._bar = tqdm(total=self._total, desc=self._desc, unit="rec", file=sys.stderr,
                             mininterval=0.5, dynamic_ncols=True)
        self._bar.update(count - self._bar.n)

    def __enter__(self) -> "_Progress":
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()


# ----------------------------------------------------------------------------- generate

def cmd_generate(args: argparse.Namespace) -> int:
    from core.data.shards import check_output_dir, write_dataset
    from core.presets import get_preset

    check_output_dir(args.out, overwrite=args.overwrite)
    check_creatable_dir(args.out, "--out")

    preset = get_preset(args.preset)
    if args.episodes >= SEED_STRIDE:
        raise DataError(f"--episodes must be below {SEED_STRIDE} (record seeds would overlap the next --seed)")
    T, V = args.frames or preset.num_frames, args.views or preset.num_views
    record_bytes = T * V * preset.camera.H * preset.camera.W * RECORD_BYTES_PER_PIXEL
    if record_bytes > MAX_RECORD_BYTES:
        raise DataError(f"--views {V} × --frames {T} at preset {preset.name} ({preset.camera.H}×{preset.camera.W}): "
                        f"one record's images would take {record_bytes / 2**30:.1f} GiB in memory, over the "
                        f"{MAX_RECORD_BYTES / 2**30:.0f} GiB limit; use fewer views or frames")

    from services.cli.render_pool import RecordSpec, default_jobs, render_records

    world_overrides = _world_overrides(args)
    specs = [RecordSpec(preset=preset.name, seed=episode_seed(args.seed, i), num_views=args.views,
                        num_frames=args.frames,
                        moving_ego={"on": True, "off": False, "mixed": i % 2 == 1}[args.moving_ego],
                        sparse_depth=args.sparse_depth, noise=args.noise, world_overrides=world_overrides)
             for i in range(args.episodes)]
    jobs = args.jobs or default_jobs(records=args.episodes,
                                     pixels_per_record=T * V * preset.camera.H * preset.camera.W)
    jobs = min(jobs, args.episodes)

    generator = {
        "source": "synthetic", "episodes": args.episodes,
        "num_views": args.views or preset.num_views, "num_frames": args.frames or preset.num_frames,
        "moving_ego": args.moving_ego, "sparse_depth": args.sparse_depth, "noise": args.noise,
        "record_seed": f"seed*{SEED_STRIDE} + index",
    }
    if world_overrides:  # only when set, so manifests of the default world read as before
        generator["world"] = dict(world_overrides)  # tuples are written as JSON lists
    records = render_records(specs, jobs=jobs)
    try:
        with _Progress(args.episodes, f"generate {args.preset}") as progress:
            manifest = write_dataset(args.out, records, split=args.split, preset_name=preset.name,
                                     grid=preset.grid.to_dict(), generator=generator, seed=args.seed,
                                     shard_bytes=_shard_bytes(args.shard_mb), overwrite=args.overwrite,
                                     on_record=progress)
    finally:
        records.close()  # stops the render workers now, whether write_dataset finished or failed
    _print_written(args.out, manifest)
    return 0


def _world_overrides(args: argparse.Namespace) -> tuple[tuple[str, object], ...]:
    """The WorldConfig fields the options change from the preset's world, as (name, value) pairs."""
    pairs: list[tuple[str, object]] = []
    for name, value in (("exposure_std", args.exposure_jitter), ("white_balance_std", args.white_balance_jitter),
                        ("pixel_noise_std", args.pixel_noise)):
        if value > 0:
            pairs.append((name, value))
    if args.texture_scale is not None:
        lo, hi = args.texture_scale
        if lo > hi:
            raise DataError(f"--texture-scale LO HI needs LO <= HI, got {lo} {hi}")
        pairs.append(("texture_scale", (lo, hi)))
    return tuple(pairs)


def _print_written(out: Path, manifest: dict) -> None:
    total = sum(s["bytes"] for s in manifest["shards"])
    print(f"wrote {manifest['num_records']} records in {len(manifest['shards'])} shards "
          f"({_human_bytes(total)}) to {out}")


# ----------------------------------------------------------------------------- info / preview

def _human_bytes(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GB"


def _dims_text(dims: dict) -> str:
    parts = []
    for name in ("T", "V", "H", "W", "K"):
        if name in dims:
            lo, hi = dims[name]
            parts.append(f"{name}={lo}" if lo == hi else f"{name}={lo}–{hi}")
    return " ".join(parts)


def cmd_info(args: argparse.Namespace) -> int:
    from core.data.shards import ShardDataset

    dataset = ShardDataset(args.dir)  # checks that every listed shard is there with its size
    manifest = dataset.manifest
    if args.json:
        summary = {k: v for k, v in manifest.items() if k != "shards"}
        summary["shards"] = [{k: v for k, v in s.items() if k != "keys"} for s in manifest["shards"]]
        print(json.dumps(summary, indent=1))
    else:
        total = sum(s["bytes"] for s in manifest["shards"])
        grid = manifest.get("grid") or {}
        print(f"dataset    {args.dir}  ({manifest['format']} v{manifest['schema_version']})")
        print(f"split      {manifest.get('split')}")
        print(f"preset     {manifest.get('preset')}")
        print(f"records    {manifest['num_records']} in {len(manifest['shards'])} shards, {_human_bytes(total)}")
        print(f"dims       {_dims_text(manifest.get('dims', {}))}")
        if grid:
            print(f"grid       Z×Y×X = {grid['Z']}×{grid['Y']}×{grid['X']} over x [{grid['xmin']}, {grid['xmax']}] "
                  f"y [{grid['ymin']}, {grid['ymax']}] z [{grid['zmin']}, {grid['zmax']}] m")
        generator = manifest.get("generator") or {}
        print(f"generator  {' '.join(f'{k}={v}' for k, v in generator.items())}")
        print(f"seed       {manifest.get('seed')}")
        for s in manifest["shards"]:
            print(f"  {s['filename']}  {s['num_records']:>6} records  {_human_bytes(s['bytes']):>10}  "
                  f"sha256 {s['sha256'][:16]}")
    if args.verify:
        # Opening checks presence and sizes; verify() checks sha256 and decodes every record.
        result = dataset.verify()
        print(f"verified   {result['records']} records in {result['shards']} shards: "
              "sha256 and record schema OK", file=sys.stdout)
    return 0


def cmd_preview(args: argparse.Namespace) -> int:
    from core.data.shards import ShardDataset

    if args.out is None and args.rerun is None:
        raise N3dmapError("give --out FILE.png, --rerun FILE.rrd or both")
    if args.points and args.rerun is None:
        raise N3dmapError("--points applies to the Rerun recording: give --rerun FILE.rrd")
    if args.out is not None and args.out.is_dir():
        raise N3dmapError(f"--out {args.out} is a directory; give the PNG file to write (e.g. {args.out / 'preview.png'})")
    if args.out is not None:
        check_creatable_dir(args.out.parent, f"--out {args.out}: its folder")
    if args.rerun is not None:  # before reading anything: a missing extra or a bad path is the first error
        from services.viz.rerun_sdk import check_rrd_path, require_rerun
        require_rerun()
    ds = ShardDataset(args.dir)
    n = len(ds)
    if not -n <= args.index < n:
        raise N3dmapError(f"--index {args.index} is out of range for {args.dir} ({n} records)")
    record = ds[args.index]
    key = ds.key(args.index)
    title = f"{args.dir.name}: record {args.index % n} ({key}), preset {ds.manifest.get('preset')}, " \
            f"split {ds.manifest.get('split')}"
    if args.out is not None:
        from services.viz.preview import contact_sheet   # matplotlib only once there is a record to draw
        out = contact_sheet(record, args.out, title=title, grid=ds.manifest.get("grid") or None)
        print(f"wrote {out}")
    if args.rerun is not None:
        from services.viz.rerun_record import log_record
        from services.viz.rerun_sdk import close_recording, open_recording

        path = check_rrd_path(args.rerun)
        rec = open_recording(name=title, save_to=path)
        try:
            log_record(rec, record, grid=ds.manifest.get("grid") or None, points=args.points)
        finally:
            close_recording(rec)
        T, V = record["rgb"].shape[:2]
        print(f"wrote {path} ({_human_bytes(path.stat().st_size)}: {V} cameras × {T} steps; open it with `rerun {path}`)")
    return 0


# ----------------------------------------------------------------------------- import

def _run_import(args: argparse.Namespace, fn: Callable[..., dict], *, describe: Callable[[dict], str] | None = None,
                **options) -> int:
    """Run importer `fn` as the flags say; `describe(manifest)`: a line on what the source gave (printed last)."""
    from core.data.shards import check_output_dir
    from core.presets import get_preset

    check_output_dir(args.out, overwrite=args.overwrite)
    check_creatable_dir(args.out, "--out")
    preset = get_preset(args.preset)
    with _Progress(args.limit, f"import {args.import_format}") as progress:
        manifest = fn(args.src, args.out, split=args.split, preset_name=preset.name,
                      grid=preset.grid.to_dict(), limit=args.limit, shard_bytes=_shard_bytes(args.shard_mb),
                      overwrite=args.overwrite, on_record=progress, **options)
    _print_written(args.out, manifest)
    if describe is not None:
        print(describe(manifest), flush=True)
    return 0


def _tum_counts(manifest: dict) -> str:
    g = manifest["generator"]
    return (f"TUM: {g['rgb_frames']} rgb frames; {g['dropped_no_depth']} without a depth frame and "
            f"{g['dropped_no_pose']} without a pose within --max-dt {g['max_dt']:g} s skipped; "
            f"{g['associated_frames']} kept (every --frame-step); {g['windows_skipped_for_gaps']} window(s) "
            "skipped for spanning a gap")


def cmd_import_authors(args: argparse.Namespace) -> int:
    from core.data.importers.authors_npz import import_authors_npz
    return _run_import(args, import_authors_npz)


def cmd_import_kitti(args: argparse.Namespace) -> int:
    from core.data.importers.kitti import import_kitti
    return _run_import(args, import_kitti, resize=tuple(args.resize) if args.resize else None)


def cmd_import_tum(args: argparse.Namespace) -> int:
    from core.data.importers.tum import import_tum
    return _run_import(args, import_tum, describe=_tum_counts, num_frames=args.frames, frame_step=args.frame_step,
                       stride=args.stride, max_dt=args.max_dt,
                       intrinsics=tuple(args.intrinsics) if args.intrinsics else None)
