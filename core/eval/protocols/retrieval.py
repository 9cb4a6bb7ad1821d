"""2D patch and 3D feature-cube retrieval P@1/5/10 (paper appendix, "2D and 3D Correspondence";
features from core.eval.retrieval_protocol, scoring core.eval.retrieval).

Every time step of every record is one example; each contributes `per_example` query/match pairs
(the paper: 100 examples × 10 = 1000 queries, each with 999 negatives — 9 from its own example, the
rest from other scenes). Each query ranks all candidates of the pool by L2 distance.
- 3D: query cubes from the map of `query_views` (default view 0), candidates from the map of the
  other views, same voxel = true match. Needs `mapper`.
- 2D: patches of the map rendered into `target_view` (default the last) from the other views,
  against the 2D net's embedding of that view's image (or, for a regression bundle without net2d,
  the image itself). Needs `projector` (+ `net2d` for contrastive bundles).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from core.errors import ShapeError
from core.eval.protocols.inputs import record_batch
from core.eval.retrieval import precision_at_k, retrieval_pool
from core.eval.retrieval_protocol import retrieval_features_2d, retrieval_features_3d

NEEDS = ("mapper",)
KS = (1, 5, 10)


@dataclass(frozen=True, kw_only=True)
class RetrievalEvalConfig:
    per_example: int = 10               # query/match pairs per example (paper: 10)
    patch_2d: int = 5                   # side of a 2D patch in render pixels
    cube_3d: int = 3                    # side of a 3D feature cube in voxels
    query_views: tuple[int, ...] = (0,)  # views of the 3D query map (negative: from the last)
    target_view: int = -1               # view rendered for 2D retrieval (-1: the last)
    seed: int = 0                       # seed of the sampled centres


def two_d_mode(bundle) -> str | None:
    """"contrastive" (projector + net2d), "regression" (projector rendering RGB), or None with no 2D."""
    if "projector" not in bundle.modules:
        return None
    if "net2d" in bundle.modules:
        return "contrastive"
    return "regression" if bundle.modules["projector"].out_channels == 3 else None


def evaluate(bundle, records, config: RetrievalEvalConfig = RetrievalEvalConfig(), *, device) -> dict:
    """{"scores": {"3d"|"2d": {"p@1", "p@5", "p@10", "queries"}} (a kind without queries absent),
    "mode_2d", "examples", "skipped": {kind: examples with too few valid centres}, "query_views"}."""
    mapper = bundle.modules["mapper"]
    mode = two_d_mode(bundle)
    gen = torch.Generator().manual_seed(config.seed)
    pools = {"3d": ([], []), "2d": ([], [])}
    examples, skipped = 0, {"3d": 0, "2d": 0}
    for record in records:
        batch = record_batch(record, device)
        T, V = batch["rgb"].shape[1:3]
        for flag, v in [("--query-views", v) for v in config.query_views] + [("--target-view", config.target_view)]:
            if not -V <= v < V:  # negative counts from the last view
                raise ShapeError(f"{flag} {v}: the records have {V} views")
        q_views = sorted({v % V for v in config.query_views})
        c_views = [v for v in range(V) if v not in q_views]
        target = config.target_view % V
        for t in range(T):
            examples += 1
            parts = {"3d": retrieval_features_3d(mapper, batch, t, query_views=q_views, candidate_views=c_views)}
            if mode is not None:
                parts["2d"] = retrieval_features_2d(mapper, bundle.modules["projector"], bundle.modules.get("net2d"),
                                                    batch, t, target=target)
            for kind, (q, c, valid) in parts.items():
                size = config.cube_3d if kind == "3d" else config.patch_2d
                try:
                    qs, cs = retrieval_pool([q.float().cpu()], [c.float().cpu()], per_example=config.per_example,
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
            "query_views": q_views if examples else list(config.query_views)}
