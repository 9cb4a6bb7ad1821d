"""Retrieval P@K against a slow sort-based reference; patch and cube extraction."""

import pytest
import torch

from core.errors import ShapeError
from core.eval.retrieval import (extract_patches, precision_at_k, retrieval_pool, sample_centers,
                                 true_match_rank)


def slow_precision_at_k(queries, candidates, k):
    """For each query, sort the candidates by distance (ties: the true one last) and look for it."""
    hits = 0
    for i in range(len(queries)):
        d = [float(torch.dist(queries[i].double(), c.double())) for c in candidates]
        order = sorted(range(len(candidates)), key=lambda j: (d[j], j == i))
        hits += i in order[:k]
    return hits / len(queries)


def test_identical_features_retrieve_perfectly():
    feats = torch.randn(1000, 16, generator=torch.Generator().manual_seed(0))
    assert precision_at_k(feats, feats.clone()) == {"p@1": 1.0, "p@5": 1.0, "p@10": 1.0}


def test_noisy_features_match_slow_reference():
    g = torch.Generator().manual_seed(1)
    queries = torch.randn(60, 4, generator=g)
    candidates = queries + 0.8 * torch.randn(60, 4, generator=g)
    got = precision_at_k(queries, candidates, ks=(1, 5, 10))
    for k in (1, 5, 10):
        assert got[f"p@{k}"] == pytest.approx(slow_precision_at_k(queries, candidates, k))
    assert 0.0 < got["p@1"] < got["p@10"] < 1.0  # the noise makes it a real ranking problem


def test_ties_do_not_help_the_query():
    queries = torch.zeros(3, 2)
    candidates = torch.zeros(3, 2)  # every candidate equally close: the true one ranks last
    assert true_match_rank(queries, candidates).tolist() == [3, 3, 3]


def test_a_non_finite_feature_is_a_miss_not_a_hit():
    """A broken query, or a broken match, ranks last; a broken candidate does not hurt the other queries."""
    feats = torch.randn(6, 4, generator=torch.Generator().manual_seed(0))
    queries, candidates = feats.clone(), feats.clone()
    queries[2, 1] = float("nan")     # query 2 broken
    candidates[4, 0] = float("inf")  # candidate 4 broken: query 4's match, and in every other query's row
    rank = true_match_rank(queries, candidates)
    assert rank.tolist() == [1, 1, 6, 1, 6, 1]
    assert precision_at_k(queries, candidates, ks=(1,))["p@1"] == 4 / 6
    assert true_match_rank(feats, feats).tolist() == [1] * 6


def test_extract_patches_2d_and_3d_against_loops():
    g = torch.Generator().manual_seed(2)
    feat2d = torch.randn(3, 10, 12, generator=g)
    centers = sample_centers(torch.ones(10, 12, dtype=torch.bool), 5, margin=1, generator=g)  # (u, v)
    patches = extract_patches(feat2d, centers, 3)
    assert patches.shape == (5, 3 * 9)
    for n, (u, v) in enumerate(centers.tolist()):
        torch.testing.assert_close(patches[n], feat2d[:, v - 1:v + 2, u - 1:u + 2].reshape(-1))
    feat3d = torch.randn(2, 6, 5, 7, generator=g)
    valid = torch.zeros(6, 5, 7, dtype=torch.bool)
    valid[3, 2, 4] = valid[2, 2, 2] = True
    centers3 = sample_centers(valid, 2, margin=1, generator=g)  # (x, y, z)
    assert sorted(centers3.tolist()) == [[2, 2, 2], [4, 2, 3]]
    cubes = extract_patches(feat3d, centers3, 3)
    for n, (x, y, z) in enumerate(centers3.tolist()):
        torch.testing.assert_close(cubes[n], feat3d[:, z - 1:z + 2, y - 1:y + 2, x - 1:x + 2].reshape(-1))
    with pytest.raises(ShapeError):
        extract_patches(feat2d, torch.tensor([[0, 0]]), 3)
    with pytest.raises(ShapeError):
        sample_centers(valid, 3, margin=1, generator=g)


def test_pool_of_100_examples_gives_1000_pairs_and_perfect_retrieval_for_identical_maps():
    g = torch.Generator().manual_seed(3)
    maps = [torch.randn(4, 6, 3, 6, generator=g) for _ in range(100)]  # C×Z×Y×X per example
    queries, candidates = retrieval_pool(maps, [m.clone() for m in maps], per_example=10, size=3, generator=g)
    assert queries.shape == candidates.shape == (1000, 4 * 27)
    assert precision_at_k(queries, candidates)["p@1"] == 1.0
    # Unrelated candidate maps: chance level is K/1000.
    other = [torch.randn(4, 6, 3, 6, generator=g) for _ in range(100)]
    q2, c2 = retrieval_pool(maps, other, per_example=10, size=3, generator=g)
    assert precision_at_k(q2, c2)["p@10"] < 0.05
