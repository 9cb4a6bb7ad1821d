"""`n3dmap eval all`: every evaluation the bundle's modules allow, one combined report.

Each kind runs as its own command (`n3dmap eval KIND`, default options) into REPORT_DIR/<kind>/;
REPORT_DIR/report.md then holds every kind's report (headings one level down, figures linked from
their sub-directories) after a summary of what ran and what was skipped and why, and
REPORT_DIR/metrics.json holds each kind's metrics under `metrics.<kind>`, plus `skipped`.
A kind whose modules the bundle lacks is skipped; so is one that fails on this data with a user
error (e.g. records with a single time step for flow), with its message.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from core.device import resolve_device
from core.errors import N3dmapError
from core.eval.protocols import detection, egomotion, flow, moving, occupancy, retrieval
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval
from services.reports import Report

# kind -> bundle modules its protocol needs, in the order the kinds run.
KINDS: dict[str, tuple[str, ...]] = {
    "retrieval": retrieval.NEEDS,
    "detection": detection.NEEDS,
    "moving": moving.NEEDS,
    "egomotion": egomotion.NEEDS,
    "flow": flow.NEEDS,
    "occupancy": occupancy.NEEDS,
}


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "all", help="every evaluation the bundle allows, one combined report")
    parser.set_defaults(func=run)


def _demote(markdown: str, kind: str) -> str:
    """A sub-report's body for the combined report: its title dropped, headings one level down, image
    links into the kind's sub-directory, its bundle/data lines dropped."""
    lines = markdown.splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    # the combined header already names the bundle and the data
    lines = [line for line in lines if not line.startswith(("- bundle: ", "- data: "))]
    body = "\n".join("#" + line if line.startswith("#") else line for line in lines).strip()
    return re.sub(r"\]\(([A-Za-z0-9_.-]+\.png)\)", rf"]({kind}/\1)", body)


def run(args) -> int:
    from services.cli.main import CliError, build_parser

    device = resolve_device(args.device)
    next(iter(iter_records(args.data, args.max_records)))  # a bad --data fails here, before any kind runs
    bundle = load_bundle_for_eval(args.bundle, device, (), data_dir=args.data)
    have = set(bundle.modules)
    del bundle
    out = Path(args.out)
    ran, skipped = {}, {}
    for kind, needs in KINDS.items():
        missing = [m for m in needs if m not in have]
        if missing:
            skipped[kind] = f"the bundle has no {', '.join(repr(m) for m in missing)} module"
            continue
        argv = ["eval", kind, "--data", args.data, "--bundle", args.bundle, "--out", str(out / kind),
                "--device", str(device)]
        if args.max_records is not None:
            argv += ["--max-records", str(args.max_records)]
        sub_args = build_parser(argv).parse_args(argv)
        try:
            sub_args.func(sub_args)
        except (N3dmapError, CliError) as e:
            skipped[kind] = f"failed on this data: {e}"
            continue
        ran[kind] = out / kind
    report = Report(kind="all", title="n3dmap evaluation: every protocol the bundle allows", bundle=args.bundle,
                    data=args.data, settings={"max_records": args.max_records, "device": str(device),
                                              "modules": ", ".join(sorted(have))})
    report.heading("Summary")
    report.text("\n".join([f"- **{k}**: ran, report in `{k}/`" for k in ran]
                          + [f"- **{k}**: skipped — {why}" for k, why in skipped.items()]))
    metrics = {}
    for kind, directory in ran.items():
        metrics[kind] = json.loads((directory / "metrics.json").read_text())["metrics"]
        report.heading(kind.capitalize())
        report.text(_demote((directory / "report.md").read_text(), kind))
    report.metrics = metrics
    written = report.write(out)
    payload = json.loads((written / "metrics.json").read_text())
    payload["skipped"] = skipped
    (written / "metrics.json").write_text(json.dumps(payload, indent=2) + "\n")
    print(f"eval all: ran {', '.join(ran) or 'nothing'}"
          + (f"; skipped {', '.join(skipped)}" if skipped else "") + f" -> {written / 'report.md'}")
    return 0
