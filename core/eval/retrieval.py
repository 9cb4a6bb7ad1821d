"""Retrieval precision P@K for 2D patches and 3D feature cubes (paper appendix, "2D and 3D Correspondence").

Protocol: a pool of N (= 1000) query/candidate pairs, where candidate i is the one true
correspondence of query i and the other N − 1 candidates are its negatives. The paper builds the
pool from 100 test examples × 10 samples each, so every query has 9 negatives from its own view
and 990 from other scenes/locations. Each query ranks all N candidates by L2 distance; P@K is the
fraction of queries whose true correspondence is among the K nearest. A candidate at exactly the
true one's distance counts as ranked ahead of it (ties never help a query).

- 2D: queries are patches of a top-down render (the 3D→2D projection of the map) and candidates
  the patches at the same pixels of the bottom-up 2D net's features of the same view.
- 3D: queries are feature cubes of the map built from one viewpoint; candidates the cubes at the
  same `mem` location of the map built from other viewpoints of the same scene (same `ref` grid).

Feature tensors are C×H×W (2D) or C×Z×Y×X (3D) for one example; pixel centres are (u, v) and
voxel centres (x, y, z) integer indices, as everywhere in n3dmap.
"""

from __future__ import annotations

import torch

from core.errors import ShapeError, check_shape


def true_match_rank(queries: torch.Tensor, candidates: torch.Tensor) -> torch.Tensor:
    """1-based rank of each query's true candidate among all candidates by L2 distance.

    queries: N×D, candidates: N×D (candidate i is the match of query i). Returns N int64. A query whose
    distance to its own match is not finite (a NaN or inf feature on either side) ranks last, N: comparisons
    with NaN are all False, so it would otherwise have none ahead and count as a perfect retrieval; another
    candidate with a non-finite distance is never ahead of a finite match.
    """
    check_shape("queries", queries, (None, None))
    check_shape("candidates", candidates, (queries.shape[0], queries.shape[1]))
    q, c = queries.double(), candidates.double()
    dist = torch.cdist(q, c)                             # N×N, row i: query i to every candidate
    broken = ~torch.isfinite(dist.diagonal())            # N: the match's own distance is NaN or inf
    dist = torch.where(torch.isfinite(dist), dist, torch.full_like(dist, float("inf")))
    true = dist.diagonal().unsqueeze(1)                  # N×1
    ahead = (dist <= true).sum(dim=1) - 1                # others at least as close (self excluded)
    return torch.where(broken, torch.full_like(ahead, dist.shape[1]), ahead + 1)


def precision_at_k(queries: torch.Tensor, candidates: torch.Tensor, ks=(1, 5, 10)) -> dict[str, float]:
    """{"p@1": ..., "p@5": ..., "p@10": ...}: fraction of queries with their match in the top K."""
    rank = true_match_rank(queries, candidates)
    return {f"p@{k}": float((rank <= k).double().mean()) for k in ks}


def sample_centers(valid: torch.Tensor, count: int, *, margin: int, generator: torch.Generator) -> torch.Tensor:
    """`count` distinct random integer centres where `valid` is True, at least `margin` from every border.

    valid: H×W or Z×Y×X bool. Returns count×2 (u, v) or count×3 (x, y, z) int64, in (x, …) order.
    Raises ShapeError if fewer than `count` positions qualify.
    """
    if valid.dim() not in (2, 3):
        raise ShapeError(f"valid: expected H×W or Z×Y×X, got {'×'.join(map(str, valid.shape))}")
    inner = torch.zeros_like(valid, dtype=torch.bool)
    region = tuple(slice(margin, s - margin) for s in valid.shape)
    inner[region] = valid[region].bool()
    idx = inner.nonzero()                                # P×dims in (z, y, x) / (v, u) order
    if len(idx) < count:
        raise ShapeError(f"only {len(idx)} valid centres at margin {margin}, need {count}")
    pick = torch.randperm(len(idx), generator=generator)[:count]
    return idx[pick].flip(-1)                            # count×dims, now (x, y, z) / (u, v)


def extract_patches(features: torch.Tensor, centers: torch.Tensor, size: int) -> torch.Tensor:
    """Square patches (2D) or cubes (3D) of side `size` around integer centres, flattened.

    features: C×H×W with centres N×2 (u, v), or C×Z×Y×X with centres N×3 (x, y, z); every patch
    must lie inside the tensor. Returns N×(C·size^dims).
    """
    dims = features.dim() - 1
    check_shape("centers", centers, (None, dims))
    lo = size // 2
    offsets = torch.arange(size, device=features.device) - lo                      # size
    spatial = features.shape[1:]
    idx_zyx = centers.long().flip(-1)                                              # N×dims, (z,y,x)/(v,u)
    for d in range(dims):
        if (idx_zyx[:, d] - lo < 0).any() or (idx_zyx[:, d] - lo + size > spatial[d]).any():
            raise ShapeError(f"a patch of size {size} leaves the feature tensor along axis {d + 1}")
    grids = torch.meshgrid(*([offsets] * dims), indexing="ij")                     # dims × size^dims
    rel = torch.stack([g.reshape(-1) for g in grids], dim=-1)                      # S×dims
    pos = idx_zyx[:, None, :] + rel[None]                                          # N×S×dims
    flat = torch.zeros(pos.shape[:2], dtype=torch.long, device=features.device)    # N×S linear index
    for d in range(dims):
        flat = flat * spatial[d] + pos[..., d]
    values = features.reshape(features.shape[0], -1)[:, flat]                      # C×N×S
    return values.permute(1, 0, 2).reshape(len(centers), -1)                       # N×(C·S)


def retrieval_pool(query_features, candidate_features, *, per_example: int = 10, size: int,
                   generator: torch.Generator, valid=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Assemble the paper's pool: `per_example` corresponding patch pairs from each example.

    query_features[e], candidate_features[e]: C×H×W (2D) or C×Z×Y×X (3D) of example e, in
    correspondence location by location (same view for 2D; same `ref` grid for 3D). valid[e]:
    H×W / Z×Y×X bool where a centre may be drawn (e.g. observed pixels, occupied voxels), or None.
    With 100 examples × 10 this is 1000 pairs: each query then has 9 negatives from its own
    example and 990 from the others. Returns (queries N×D, candidates N×D), pair i matching.
    """
    if len(query_features) != len(candidate_features):
        raise ShapeError(f"{len(query_features)} query tensors but {len(candidate_features)} candidate tensors")
    queries, candidates = [], []
    for e, (q, c) in enumerate(zip(query_features, candidate_features)):
        if q.shape != c.shape:
            raise ShapeError(f"example {e}: query features {tuple(q.shape)} vs candidate features {tuple(c.shape)}")
        ok = torch.ones(q.shape[1:], dtype=torch.bool) if valid is None else valid[e].bool().cpu()
        centers = sample_centers(ok, per_example, margin=size // 2, generator=generator).to(q.device)
        queries.append(extract_patches(q, centers, size))
        candidates.append(extract_patches(c, centers, size))
    return torch.cat(queries), torch.cat(candidates)
