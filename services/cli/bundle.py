"""`n3dmap bundle info B [--json]`: describe a model bundle (version, preset, grid, modules, lineage, metrics).
`n3dmap bundle merge B1 B2 [...] --out OUT [--take MODULE=B]`: join bundles trained apart into one.
`n3dmap bundle flow-window B --out OUT [--refine-radius RX RY RZ] [--refine-aggregate AX AY AZ]`: the same bundle
with its flow module's full-grid step given another window (no retraining: that step has no weights that depend
on it).
"""

from __future__ import annotations

import argparse
import json

from services.cli.lineage import lineage_lines
from services.cli.paths import check_creatable_dir


def describe_bundle(path: str) -> dict:
    """A JSON-ready description of the bundle at `path` (BundleError if missing or corrupt).

    Loads the weights too, so a bundle that describes fine also loads.
    """
    from core.bundle import load_bundle

    bundle = load_bundle(path, "cpu")
    meta = bundle.meta
    modules = {name: {"kind": meta["modules"][name].get("kind", type(m).__name__),
                      "parameters": sum(p.numel() for p in m.parameters())}
               for name, m in sorted(bundle.modules.items())}
    return {
        "path": str(path),
        "version": bundle.version,
        "format_version": meta.get("format_version"),
        "n3dmap_version": meta.get("n3dmap_version"),
        "preset": bundle.preset.name,
        "grid": bundle.preset.grid.to_dict(),
        "modules": modules,
        "total_parameters": sum(m["parameters"] for m in modules.values()),
        "provenance": meta.get("provenance", {}),
        "metrics": meta.get("metrics", {}),
    }


def format_description(d: dict) -> str:
    grid = d["grid"] or {}
    lines = [f"bundle {d['path']}",
             f"  version  {d['version']}",
             f"  preset   {d['preset']}"]
    if grid:
        counts = "×".join(str(grid.get(k, "?")) for k in ("Z", "Y", "X"))
        bounds = ", ".join(f"{a} [{grid.get(a + 'min')}, {grid.get(a + 'max')}]" for a in "xyz")
        lines.append(f"  grid     Z×Y×X {counts}; {bounds} m")
    lines.append(f"  modules  ({d['total_parameters']:,} parameters)")
    width = max((len(n) for n in d["modules"]), default=0)
    for name, m in d["modules"].items():
        lines.append(f"    {name:<{width}}  {m['kind']:<20} {m['parameters']:>12,}")
    if d["provenance"]:
        # The provenance nests every ancestor's under "parents": one line per run reads; --json has it all.
        lines.append("  lineage  (this bundle's run, then each bundle it was initialised from; --json: everything)")
        lines += [f"    {line}" for line in lineage_lines(d["provenance"], d["path"])]
    if d["metrics"]:
        lines.append("  metrics")
        lines += [f"    {k}: {v:.6g}" if isinstance(v, float) else f"    {k}: {v}"
                  for k, v in sorted(d["metrics"].items())]
    return "\n".join(lines)


def _info(args: argparse.Namespace) -> int:
    d = describe_bundle(args.bundle)
    print(json.dumps(d, indent=1, sort_keys=True) if args.json else format_description(d))
    return 0


def _check_new_bundle_dir(out) -> None:
    """--out of a command that writes a bundle: creatable, and not already holding one (never overwritten)."""
    from core.bundle import BUNDLE_JSON
    from services.cli.errors import CliError

    check_creatable_dir(out, "--out")
    if (out / BUNDLE_JSON).exists():
        raise CliError(f"--out {out} already holds a bundle; write into a new directory (nothing was written)")


def _merge(args: argparse.Namespace) -> int:
    from pathlib import Path

    from core.bundle import foreign_mapper_readers, load_bundle, merge_bundles, parent_provenance, save_bundle
    from services.cli.errors import CliError
    from services.training.job import git_commit

    paths = [Path(b) for b in args.bundles]
    out = Path(args.out)
    _check_new_bundle_dir(out)
    if any(out.resolve() == p.resolve() for p in paths):
        raise CliError(f"--out {out} is one of the bundles being merged; merge into a new directory")
    take: dict[str, int] = {}
    for item in args.take or []:
        name, sep, where = item.partition("=")
        if not sep or not name or not where:
            raise CliError(f"--take {item!r}: expected MODULE=B, with B one of the bundles given")
        matches = [i for i, p in enumerate(paths) if p.resolve() == Path(where).resolve()]
        if not matches:
            raise CliError(f"--take {item!r}: {where} is not one of the bundles given ({', '.join(map(str, paths))})")
        take[name] = matches[0]
    bundles = [load_bundle(p, "cpu") for p in paths]
    modules, sources = merge_bundles(bundles, take=take)
    provenance = {"task": "merge", "sources": {name: str(paths[i]) for name, i in sorted(sources.items())},
                  "git_commit": git_commit(), "parents": [parent_provenance(b) for b in bundles]}
    save_bundle(out, modules=modules, preset=bundles[0].preset, provenance=provenance)
    width = max(len(n) for n in modules)
    print(f"merged {len(modules)} module(s) into {out}:")
    for name in sorted(modules):
        print(f"  {name:<{width}}  from {paths[sources[name]]}")
    for name in foreign_mapper_readers(bundles, sources):
        print(f"warning: {name} (from {paths[sources[name]]}) reads mapper features, but the mapper kept is "
              f"{paths[sources['mapper']]}'s, not the one it was trained on")
    return 0


def _flow_window(args: argparse.Namespace) -> int:
    """Write a copy of bundle B whose flow module's grid step has the given window and cost box. Why this works
    without retraining: the step (core.models.flow3d, `refine`) is a soft-argmax over cosines of the learned
    projection's features; its only weights (the sharpness β, the zero-motion bonus) are per step, not per
    displacement, so the module's weights load unchanged into the wider step (strict load below). Measured on
    the small report's ±1-trained input-volume flows (docs/findings.md, "The wide step is now the default")."""
    from pathlib import Path

    from core.bundle import load_bundle, parent_provenance, save_bundle
    from core.models.flow3d import Flow3D
    from services.cli.errors import CliError
    from services.training.job import git_commit

    source, out = Path(args.bundle), Path(args.out)
    _check_new_bundle_dir(out)   # also refuses --out B itself: B holds a bundle
    bundle = load_bundle(source, "cpu")
    if "flow" not in bundle.modules:
        raise CliError(f"{source} has no flow module (modules: {', '.join(sorted(bundle.modules))})")
    old = bundle.modules["flow"]
    if not (old.refine and old.finest > 0):
        raise CliError(f"{source}'s flow module has no full-grid step (refine {old.refine}, finest {old.finest}): "
                       "its windows are its decoders', which have weights per displacement; retrain it instead")
    config = old.config()
    if args.refine_radius is not None:
        config["refine_radius"] = list(args.refine_radius)
    if args.refine_aggregate is not None:
        config["refine_aggregate"] = list(args.refine_aggregate)
    try:
        new = Flow3D(**config)
    except ValueError as e:
        raise CliError(f"--refine-radius / --refine-aggregate: {e}") from None
    new.load_state_dict(old.state_dict(), strict=True)   # every weight carries over, none is added
    new.eval()
    provenance = {"task": "flow-window", "source": str(source), "git_commit": git_commit(),
                  "refine_radius": config["refine_radius"], "refine_aggregate": config["refine_aggregate"],
                  "parents": [parent_provenance(bundle)]}
    save_bundle(out, modules={**bundle.modules, "flow": new}, preset=bundle.preset, provenance=provenance,
                metrics=bundle.meta.get("metrics", {}))
    print(f"wrote {out}: flow grid step {list(old.refine_radius)} (cost box {list(old.refine_aggregate)}) -> "
          f"{config['refine_radius']} (cost box {config['refine_aggregate']}); every other module as in {source}")
    return 0


def register(subparsers) -> None:
    bundle = subparsers.add_parser("bundle", help="inspect model bundles", description=__doc__.splitlines()[0])
    actions = bundle.add_subparsers(dest="action", metavar="ACTION", required=True)
    info = actions.add_parser("info", help="describe a bundle")
    info.add_argument("bundle", metavar="B", help="bundle directory (bundle.json + weights)")
    info.add_argument("--json", action="store_true",
                      help="print the full record as JSON (with every ancestor's whole provenance)")
    info.set_defaults(func=_info)
    merge = actions.add_parser(
        "merge", help="join bundles trained apart into one (e.g. a benchmark's flow and egomotion stages)",
        description="Write one bundle holding every module of the given bundles (all of one preset). A module "
                    "that several bundles hold is kept once when the copies are equal bit for bit; where they "
                    "differ, --take says which to keep. Modules that read mapper features (occupancy, detector, "
                    "flow over features) need the mapper they were trained on: a warning names any that would not "
                    "get it.")
    merge.add_argument("bundles", metavar="B", nargs="+", help="bundle directories (at least two)")
    merge.add_argument("--out", required=True, help="new bundle directory (refused if it already holds a bundle)")
    merge.add_argument("--take", action="append", metavar="MODULE=B",
                       help="keep MODULE from bundle B (one of those given) where the copies differ; repeatable")
    merge.set_defaults(func=_merge)
    from services.cli.argtypes import non_negative_int
    window = actions.add_parser(
        "flow-window", help="copy a bundle with its flow module's full-grid step given another window",
        description="Write a copy of bundle B whose flow module's last, full-grid correlator step searches "
                    "another window (and averages its costs over another box). No retraining: that step has no "
                    "weights that depend on its window. Bundles trained before session 36 have a ±1 step, which "
                    "misses objects moving more than ~1.5 voxels a step; `--refine-radius 3 1 3 "
                    "--refine-aggregate 1 1 1` (the defaults here, and training's since) raised the small "
                    "report's input-volume flows' moving-object AP3D@0.5 from 0.30-0.41 to 0.80-0.93 on "
                    "held-out records, at ~2.3x the flow module's time.")
    window.add_argument("bundle", metavar="B", help="bundle directory with a flow module")
    window.add_argument("--out", required=True, help="new bundle directory (refused if it already holds a bundle)")
    window.add_argument("--refine-radius", type=non_negative_int, nargs=3, default=(3, 1, 3),
                        metavar=("RX", "RY", "RZ"), help="the grid step's window in voxels (default 3 1 3)")
    window.add_argument("--refine-aggregate", type=non_negative_int, nargs=3, default=(1, 1, 1),
                        metavar=("AX", "AY", "AZ"), help="the box its costs are averaged over (default 1 1 1)")
    window.set_defaults(func=_flow_window)
