"""Distance-weighted margin loss: fast code against slow per-element references."""

import math

import pytest
import torch
import torch.nn.functional as F

from core.losses.contrastive import (ContrastiveConfig, margin_loss, negative_weights, sample_negatives,
                                     sample_positions, view_contrastive_loss)
from core.losses.dense import dense_l2
from core.losses.occupancy import balanced_occupancy_loss
from core.losses.regression import rgb_l1


def _unit(*shape, seed=0):
    return F.normalize(torch.randn(*shape, generator=torch.Generator().manual_seed(seed)), dim=1)


def _weights_reference(emb, labels, cutoff, nonzero):
    """Per-row loop over Wu et al.'s formula with plain math."""
    N, n = emb.shape
    P = torch.zeros(N, N, dtype=torch.float64)
    for i in range(N):
        row = []
        for j in range(N):
            d = math.sqrt(max(float(((emb[i] - emb[j]) ** 2).sum()), 0.0) + 1e-8)
            d = min(max(d, cutoff), 2.0 - 1e-4)
            ok = labels[i] != labels[j] and d < nonzero
            row.append(math.exp((2.0 - n) * math.log(d) - (n - 3) / 2.0 * math.log(1 - d * d / 4)) if ok else 0.0)
        if sum(row) == 0:  # fallback: uniform over the other labels
            row = [1.0 if labels[i] != labels[j] else 0.0 for j in range(N)]
        s = sum(row)
        P[i] = torch.tensor([r / s for r in row], dtype=torch.float64)
    return P


def test_negative_weights_match_reference():
    emb = _unit(24, 5, seed=1)
    labels = torch.arange(12).repeat_interleave(2)
    fast = negative_weights(emb, labels, cutoff=0.5, nonzero_loss_cutoff=1.4).double()
    slow = _weights_reference(emb.double(), labels.tolist(), 0.5, 1.4)
    assert torch.allclose(fast, slow, atol=1e-5)
    assert (fast[labels[:, None] == labels[None, :]] == 0).all()  # never the same pair


def test_sampler_draws_valid_indices_following_the_weights():
    emb = _unit(16, 4, seed=2)
    labels = torch.arange(8).repeat_interleave(2)
    probs = negative_weights(emb, labels)
    draws = 2000
    gen = torch.Generator().manual_seed(0)
    counts = torch.zeros(16, 16)
    for _ in range(draws):
        idx = sample_negatives(emb, labels, generator=gen)
        assert (labels[idx] != labels).all()
        counts[torch.arange(16), idx] += 1
    freq = counts / draws
    # binomial std of a frequency is sqrt(p(1-p)/n) <= 0.012; allow ~4 sigma
    assert (freq - probs).abs().max() < 0.05
    assert (counts[probs == 0] == 0).all()


def test_margin_loss_matches_reference():
    a, p, n = _unit(50, 6, seed=3), _unit(50, 6, seed=4), _unit(50, 6, seed=5)
    beta, margin = 1.2, 0.2
    total, active = 0.0, 0
    for i in range(50):
        dp = math.sqrt(float(((p[i] - a[i]) ** 2).sum()) + 1e-8)
        dn = math.sqrt(float(((n[i] - a[i]) ** 2).sum()) + 1e-8)
        for term in (max(dp - beta + margin, 0.0), max(beta - dn + margin, 0.0)):
            total += term
            active += term > 0
    assert margin_loss(a, p, n, beta=beta, margin=margin).item() == pytest.approx(total / max(active, 1), rel=1e-5)


def test_view_contrastive_loss_matches_reference_and_samples_only_valid():
    B, C = 2, 6
    top, bot = _unit(B, C, 4, 5, 3, seed=6), _unit(B, C, 4, 5, 3, seed=7)
    valid = (torch.rand(B, 1, 4, 5, 3, generator=torch.Generator().manual_seed(8)) > 0.6).float()
    cfg = ContrastiveConfig(samples=10)
    fast = view_contrastive_loss(top, bot, valid, cfg, torch.Generator().manual_seed(9))

    # reference: replay the same draws, then gather and pair with explicit loops
    gen = torch.Generator().manual_seed(9)
    rows, cols = sample_positions(valid.reshape(B, -1) > 0.5, cfg.samples, gen)
    assert all(valid.reshape(B, -1)[r, c] == 1 for r, c in zip(rows.tolist(), cols.tolist()))
    emb, labels = [], []
    for k, (r, c) in enumerate(zip(rows.tolist(), cols.tolist())):
        emb += [top.reshape(B, C, -1)[r, :, c], bot.reshape(B, C, -1)[r, :, c]]
        labels += [(r, c), (r, c)]   # one label per (example, position)
    labels = [sorted(set(labels)).index(label) for label in labels]
    emb = torch.stack(emb)
    neg = sample_negatives(emb, torch.tensor(labels), generator=gen)
    partner = [i + 1 if i % 2 == 0 else i - 1 for i in range(len(labels))]
    slow = margin_loss(emb, emb[partner], emb[neg])
    assert fast.item() == pytest.approx(slow.item(), rel=1e-6)


def test_a_position_drawn_twice_is_never_its_own_negative(monkeypatch):
    # 3 valid positions and 16 samples: positions are drawn with replacement; a duplicate of the anchor's
    # position (distance 0: the sampler's favourite) must not be its negative — that would push the
    # positive pair apart
    B, C, P = 1, 4, 12
    top, bot = _unit(B, C, P, seed=3), _unit(B, C, P, seed=4)
    valid = torch.zeros(B, 1, P)
    valid[0, 0, [2, 5, 9]] = 1.0
    cfg = ContrastiveConfig(samples=16)
    seen = {}
    original = sample_negatives

    def spy(emb, labels, **kwargs):
        seen["emb"], seen["labels"] = emb, labels
        seen["neg"] = original(emb, labels, **kwargs)
        return seen["neg"]

    monkeypatch.setattr("core.losses.contrastive.sample_negatives", spy)
    loss = view_contrastive_loss(top, bot, valid, cfg, torch.Generator().manual_seed(0))
    assert torch.isfinite(loss)
    labels, neg = seen["labels"], seen["neg"]
    assert len(set(labels.tolist())) == 3                        # 3 positions, 32 embeddings
    assert bool((labels[neg] != labels).all())                   # every negative is another position
    # one valid position only: no second pair to be a negative, the loss is 0 with a gradient path
    one = torch.zeros(B, 1, P)
    one[0, 0, 4] = 1.0
    assert view_contrastive_loss(top, bot, one, cfg).item() == 0.0


def test_view_contrastive_loss_without_valid_positions_is_zero_with_gradient():
    top = _unit(1, 4, 3, 3, seed=1).requires_grad_()
    loss = view_contrastive_loss(top, _unit(1, 4, 3, 3, seed=2), torch.zeros(1, 1, 3, 3))
    loss.backward()
    assert loss.item() == 0.0 and top.grad is not None


def test_dense_l2_and_rgb_l1_match_loops():
    a, b = torch.randn(2, 3, 4, 5), torch.randn(2, 3, 4, 5)
    valid = (torch.rand(2, 1, 4, 5) > 0.5).float()
    num = sum(float(((a[i, :, y, x] - b[i, :, y, x]) ** 2).sum())
              for i in range(2) for y in range(4) for x in range(5) if valid[i, 0, y, x])
    assert dense_l2(a, b, valid).item() == pytest.approx(num / valid.sum().item(), rel=1e-5)
    num = sum(float((a[i, :, y, x] - b[i, :, y, x]).abs().sum())
              for i in range(2) for y in range(4) for x in range(5) if valid[i, 0, y, x])
    assert rgb_l1(a, b, valid).item() == pytest.approx(num / (3 * valid.sum().item()), rel=1e-5)


def test_balanced_occupancy_loss_matches_reference():
    logits = torch.randn(1, 1, 3, 4, 5)
    occ = (torch.rand(1, 1, 3, 4, 5) > 0.8).float()
    free = (torch.rand(1, 1, 3, 4, 5) > 0.4).float()
    pos, neg = [], []
    for z, l in enumerate(logits.flatten().tolist()):
        p = 1 / (1 + math.exp(-l))
        if occ.flatten()[z]:
            pos.append(-math.log(p))
        elif free.flatten()[z]:
            neg.append(-math.log(1 - p))
    ref = (sum(pos) / len(pos) + sum(neg) / len(neg)) / 2
    assert balanced_occupancy_loss(logits, occ, free).item() == pytest.approx(ref, rel=1e-5)
