"""`n3dmap eval retrieval`: 2D patch and 3D feature-cube retrieval P@1/5/10 (paper appendix,
"2D and 3D Correspondence"; features from core.eval.retrieval_protocol, scoring core.eval.retrieval).

Every time step of every record is one example; each contributes `--per-example` query/match pairs
(the paper: 100 examples × 10 = 1000 queries, each with 999 negatives — 9 from its own example, the
rest from other scenes). Each query ranks all candidates of the pool by L2 distance.
- 3D: query cubes from the map of `--query-views` (default view 0), candidates from the map of the
  other views, same voxel = true match. Needs `mapper`.
- 2D: patches of the map rendered into `--target-view` (default the last) from the other views,
  against the 2D net's embedding of that view's image (or, for a regression bundle without net2d,
  the image itself). Needs `projector` (+ `net2d` for contrastive bundles).
"""

from __future__ import annotations

import torch

from core.errors import ShapeError
from core.eval.retrieval import precision_at_k, retrieval_pool
from core.eval.retrieval_protocol import retrieval_features_2d, retrieval_features_3d
from services.cli.argtypes import positive_int
from services.cli.eval import add_eval_parser, iter_records, load_bundle_for_eval, resolve_device
from services.cli.eval_tasks.common import record_batch
from services.reports import Report

NEEDS = ("mapper",)
KS = (1, 5, 10)


def register(kinds) -> None:
    parser = add_eval_parser(kinds, "retrieval", help="2D patch and 3D feature-cube retrieval P@1/5/10")
    parser.add_argument("--per-example", type=positive_int, default=10, help="query/match pairs per example (paper: 10)")
    parser.add_argument("--patch-2d", type=positive_int, default=5, help="side of a 2D patch in render pixels")
    parser.add_argument("--cube-3d", type=positive_int, default=3, help="side of a 3D feature cube in voxels")
    parser.add_argument("--query-views", type=int, nargs="+", default=[0], help="views of the 3D query map")
    parser.add_argument("--target-view", type=int, default=-1, help="view rendered for 2D retrieval (-1: last)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampled centres")
    parser.set_defaults(func=run)


def two_d_mode(bundle) -> str | None:
    """"contrastive" (projector + net2d), "regression" (projector rendering RGB), or None with no 2D."""
    if "projector" not in bundle.modules:
        return None
    if "net2d" in bundle.modules:
        return "contrastive"
    return "regression" if bundle.modules["projector"].out_channels == 3 else None


def evaluate(bundle, records, *, device, per_example=10, patch_2d=5, cube_3d=3, query_views=(0,),
             target_view=-1, seed=0) -> dict:
    mapper = bundle.modules["mapper"]
    mode = two_d_mode(bundle)
    gen = torch.Generator().manual_seed(seed)
    pools = {"3d": ([], []), "2d": ([], [])}
    examples, skipped = 0, {"3d": 0, "2d": 0}
    for record in records:
        batch = record_batch(record, device)
        T, V = batch["rgb"].shape[1:3]
        for flag, v in [("--query-views", v) for v in query_views] + [("--target-view", target_view)]:
            if not -V <= v < V:  # negative counts from the last view
                raise ShapeError(f"{flag} {v}: the records have {V} views")
        q_views = sorted({v % V for v in query_views})
        c_views = [v for v in range(V) if v not in q_views]
        target = target_view % V
        for t in range(T):
            examples += 1
            parts = {"3d": retrieval_features_3d(mapper, batch, t, query_views=q_views, candidate_views=c_views)}
            if mode is not None:
                parts["2d"] = retrieval_features_2d(mapper, bundle.modules["projector"], bundle.modules.get("net2d"),
                                                    batch, t, target=target)
            for kind, (q, c, valid) in parts.items():
                size = cube_3d if kind == "3d" else patch_2d
                try:
                    qs, cs = retrieval_pool([q.float().cpu()], [c.float().cpu()], per_example=per_example,
                                            size=size, generator=gen, valid=[valid.cpu()])
                except ShapeError:  # too few observed surface voxels / pixels in this example
                    skipped[kind] += 1
                    continue
                pools[kind][0].append(qs)
                pools[kind][1].append(cs)
    scores = {}
    for kind, (qs, cs) in pools.items():
        if qs:
            q, c = torch.cat(qs), torch.cat(cs)
            scores[kind] = {**precision_at_k(q, c, KS), "queries": int(len(q))}
    return {"scores": scores, "mode_2d": mode, "examples": examples, "skipped": skipped,
            "query_views": q_views if examples else list(query_views)}


def build_report(bundle, records, *, device, bundle_path=None, data_path=None, max_records=None, **options) -> Report:
    result = evaluate(bundle, records, device=device, **options)
    report = Report(kind="retrieval", title="2D and 3D retrieval evaluation", bundle=bundle_path, data=data_path,
                    settings={"max_records": max_records, "examples": result["examples"], "device": str(device),
                              "per_example": options.get("per_example", 10),
                              "patch_2d_px": options.get("patch_2d", 5), "cube_3d_voxels": options.get("cube_3d", 3),
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
            report.text(f"{n} example(s) skipped for {kind.upper()}: fewer than {options.get('per_example', 10)} "
                        "valid centres away from the border.")
    return report


def run(args) -> int:
    device = resolve_device(args.device)
    bundle = load_bundle_for_eval(args.bundle, device, NEEDS, data_dir=args.data)
    report = build_report(bundle, iter_records(args.data, args.max_records), device=device, bundle_path=args.bundle,
                          data_path=args.data, max_records=args.max_records, per_example=args.per_example,
                          patch_2d=args.patch_2d, cube_3d=args.cube_3d, query_views=args.query_views,
                          target_view=args.target_view, seed=args.seed)
    out = report.write(args.out)
    for kind, s in report.metrics["retrieval"].items():
        print(f"retrieval {kind.upper()}: {s['queries']} queries, "
              + " ".join(f"P@{k} {s[f'p@{k}']:.3f}" for k in KS))
    print(f"-> {out / 'report.md'}")
    return 0
