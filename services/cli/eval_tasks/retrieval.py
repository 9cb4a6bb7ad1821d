"""`n3dmap eval retrieval`: 2D patch and 3D feature-cube retrieval P@1/5/10 (paper appendix,
"2D and 3D Correspondence"; the protocol is core.eval.protocols.retrieval: every time step one example,
`--per-example` query/match pairs each, ranked by L2 distance over the pooled candidates).
"""

from __future__ import annotations

from core.device import resolve_device
from core.eval.protocols.retrieval import KS, NEEDS, RetrievalEvalConfig, evaluate
from services.cli.argtypes import positive_int
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval
from services.reports import Report


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "retrieval", help="2D patch and 3D feature-cube retrieval P@1/5/10")
    parser.add_argument("--per-example", type=positive_int, default=10, help="query/match pairs per example (paper: 10)")
    parser.add_argument("--patch-2d", type=positive_int, default=5, help="side of a 2D patch in render pixels")
    parser.add_argument("--cube-3d", type=positive_int, default=3, help="side of a 3D feature cube in voxels")
    parser.add_argument("--query-views", type=int, nargs="+", default=[0], help="views of the 3D query map")
    parser.add_argument("--target-view", type=int, default=-1, help="view rendered for 2D retrieval (-1: last)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampled centres")
    parser.set_defaults(func=run)


def build_report(bundle, records, config: RetrievalEvalConfig = RetrievalEvalConfig(), *, device, bundle_path=None,
                 data_path=None, max_records=None) -> Report:
    result = evaluate(bundle, records, config, device=device)
    report = Report(kind="retrieval", title="2D and 3D retrieval evaluation", bundle=bundle_path, data=data_path,
                    settings={"max_records": max_records, "examples": result["examples"], "device": str(device),
                              "per_example": config.per_example,
                              "patch_2d_px": config.patch_2d, "cube_3d_voxels": config.cube_3d,
                              "query_views_3d": str(result["query_views"]), "mode_2d": result["mode_2d"] or "none"})
    report.metrics = {"retrieval": result["scores"], "retrieval_skipped_examples": result["skipped"]}
    report.text("Nearest-neighbour retrieval by L2 distance over a pool of query/match pairs (every other "
                "candidate is a negative: from the same example and from other scenes). P@K: the fraction of "
                "queries whose true match is among the K nearest candidates; a tie counts against the query. "
                "With Q queries, chance P@K is K/Q.")
    rows = []
    for kind, label in (("2d", "2D patches (top-down render vs bottom-up)"), ("3d", "3D feature cubes (view subsets)")):
        s = result["scores"].get(kind)
        if s is None:
            rows.append([label, None, None, None, 0])
        else:
            rows.append([label, *[s[f"p@{k}"] for k in KS], s["queries"]])
    report.table(["retrieval", *[f"P@{k}" for k in KS], "queries"], rows)
    if result["mode_2d"] is None:
        report.text("2D retrieval skipped: the bundle has no `projector` (or a projector without `net2d` that "
                    "does not render RGB).")
    elif result["mode_2d"] == "regression":
        report.text("2D retrieval of a regression bundle: its projector renders RGB and it has no 2D net, so "
                    "rendered RGB patches are matched against the image's own (centred) RGB patches.")
    for kind, n in result["skipped"].items():
        if n:
            report.text(f"{n} example(s) skipped for {kind.upper()}: fewer than {config.per_example} "
                        "valid centres away from the border.")
    return report


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    config = RetrievalEvalConfig(per_example=args.per_example, patch_2d=args.patch_2d, cube_3d=args.cube_3d,
                                 query_views=tuple(args.query_views), target_view=args.target_view, seed=args.seed)
    report = build_report(bundle, iter_records(args.data, args.max_records), config, device=device,
                          bundle_path=args.bundle, data_path=args.data, max_records=args.max_records)
    out = report.write(args.out)
    for kind, s in report.metrics["retrieval"].items():
        print(f"retrieval {kind.upper()}: {s['queries']} queries, "
              + " ".join(f"P@{k} {s[f'p@{k}']:.3f}" for k in KS))
    print(f"-> {out / 'report.md'}")
    return 0
