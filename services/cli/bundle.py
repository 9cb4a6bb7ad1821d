"""`n3dmap bundle info B [--json]`: describe a model bundle (version, preset, grid, modules, lineage, metrics)."""

from __future__ import annotations

import argparse
import json

from services.cli.lineage import lineage_lines


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


def register(subparsers) -> None:
    bundle = subparsers.add_parser("bundle", help="inspect model bundles", description=__doc__.splitlines()[0])
    actions = bundle.add_subparsers(dest="action", metavar="ACTION", required=True)
    info = actions.add_parser("info", help="describe a bundle")
    info.add_argument("bundle", metavar="B", help="bundle directory (bundle.json + weights)")
    info.add_argument("--json", action="store_true",
                      help="print the full record as JSON (with every ancestor's whole provenance)")
    info.set_defaults(func=_info)
