"""View-contrastive margin loss with distance-weighted negative sampling (paper §3.2 + appendix).

Top-down and bottom-up feature tensors are aligned, so each sampled position gives a positive pair.
Per example we sample `samples` positions where the target is valid; all 2·B·S embeddings are pooled
across the batch, each one is an anchor, its partner is the positive, and one negative is drawn from
every other pair with the distance-weighted sampler of Wu et al. 2017 ("Sampling matters in deep
embedding learning"): weights 1/q(d) with q(d) ∝ d^(n−2) (1 − d²/4)^((n−3)/2) the density of
distances between uniform points on the unit sphere in R^n, distances clamped below at `cutoff`
(0.5) and zero weight at d ≥ `nonzero_loss_cutoff` (1.4, such negatives give no loss). The margin
loss then is  relu(d_ap − β + α) + relu(β − d_an + α)  averaged over the terms that are non-zero,
with boundary β = 1.2 and margin α = 0.2. Embeddings are expected to be unit length.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from core.errors import ShapeError
from core.precision import full_precision


@dataclass(frozen=True)
class ContrastiveConfig:
    """Hyperparameters of the margin loss and its sampler (paper values by default)."""

    samples: int = 960
    beta: float = 1.2
    margin: float = 0.2
    cutoff: float = 0.5
    nonzero_loss_cutoff: float = 1.4


@full_precision  # |a|² + |b|² − 2a·b cancels: float32 under autocast
def pairwise_distances(emb: torch.Tensor) -> torch.Tensor:
    """emb: N×C -> N×N Euclidean distances (sqrt with a small floor so gradients stay finite)."""
    sq = (emb * emb).sum(dim=1)
    d2 = (sq[:, None] + sq[None, :] - 2.0 * emb @ emb.t()).clamp(min=0.0)  # N×N
    return torch.sqrt(d2 + 1e-8)


def negative_weights(emb: torch.Tensor, labels: torch.Tensor, *, cutoff: float = 0.5,
                     nonzero_loss_cutoff: float = 1.4) -> torch.Tensor:
    """Distance-weighted negative sampling probabilities.

    emb: N×C unit embeddings; labels: N ints (same label = same pair, never a negative).
    Returns N×N row-stochastic probabilities. A row whose candidates all lie beyond
    `nonzero_loss_cutoff` falls back to uniform over its candidates (as Wu et al.'s reference code).
    """
    N, n = emb.shape
    with torch.no_grad():
        d = pairwise_distances(emb.float()).clamp(min=cutoff, max=2.0 - 1e-4)  # N×N
        # log of 1/q(d) for q the distance density on the unit sphere in R^n
        log_w = (2.0 - n) * torch.log(d) - ((n - 3) / 2.0) * torch.log(1.0 - 0.25 * d * d)
        candidate = labels[:, None] != labels[None, :]              # N×N
        allowed = candidate & (d < nonzero_loss_cutoff)
        log_w = log_w.masked_fill(~allowed, float("-inf"))
        empty = ~allowed.any(dim=1, keepdim=True)                   # N×1
        log_w = torch.where(empty & candidate, torch.zeros_like(log_w), log_w)
        log_w = log_w - log_w.max(dim=1, keepdim=True).values.clamp(min=-1e30)
        w = torch.exp(log_w)
        return w / w.sum(dim=1, keepdim=True).clamp(min=1e-30)


def sample_negatives(emb: torch.Tensor, labels: torch.Tensor, *, cutoff: float = 0.5,
                     nonzero_loss_cutoff: float = 1.4, generator: torch.Generator | None = None) -> torch.Tensor:
    """One negative index per anchor, drawn from `negative_weights`. emb: N×C, labels: N -> N long."""
    probs = negative_weights(emb, labels, cutoff=cutoff, nonzero_loss_cutoff=nonzero_loss_cutoff)
    # Inverse-CDF draw: one uniform per row and a binary search. torch.multinomial draws an exponential
    # per matrix entry, several times slower on CPU for the 1920×1920 (small) .. 7680² (paper) matrices.
    # With right=True the first index whose CDF exceeds u always has non-zero probability.
    cdf = probs.cumsum(dim=1)                                                  # N×N
    u = torch.rand(probs.shape[0], 1, generator=generator,
                   device=generator.device if generator is not None else probs.device)
    u = u.to(probs.device) * cdf[:, -1:]                                       # N×1
    return torch.searchsorted(cdf, u, right=True).squeeze(1).clamp(max=probs.shape[1] - 1)


def margin_loss(anchor: torch.Tensor, positive: torch.Tensor, negative: torch.Tensor, *,
                beta: float = 1.2, margin: float = 0.2) -> torch.Tensor:
    """anchor, positive, negative: N×C -> scalar mean over the non-zero hinge terms (0 if none)."""
    d_ap = torch.sqrt(((positive - anchor) ** 2).sum(dim=1) + 1e-8)  # N
    d_an = torch.sqrt(((negative - anchor) ** 2).sum(dim=1) + 1e-8)  # N
    pos_loss = torch.relu(d_ap - beta + margin)
    neg_loss = torch.relu(beta - d_an + margin)
    active = (pos_loss > 0).sum() + (neg_loss > 0).sum()
    return (pos_loss.sum() + neg_loss.sum()) / active.clamp(min=1).to(anchor.dtype)


def sample_positions(valid: torch.Tensor, samples: int,
                     generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """valid: B×P bool -> (example index K, position index K) of up to `samples` valid positions per
    example (without replacement when enough are valid, with replacement otherwise; none from an
    example with no valid position)."""
    rows, cols = [], []
    valid_cpu = valid.detach().cpu()
    for b in range(valid.shape[0]):
        idx = torch.nonzero(valid_cpu[b], as_tuple=False).squeeze(1)  # Pv
        if idx.numel() == 0:
            continue
        if idx.numel() >= samples:
            pick = torch.randperm(idx.numel(), generator=generator)[:samples]
        else:
            pick = torch.randint(idx.numel(), (samples,), generator=generator)
        cols.append(idx[pick])
        rows.append(torch.full((samples,), b, dtype=torch.long))
    if not rows:
        empty = torch.zeros(0, dtype=torch.long, device=valid.device)
        return empty, empty
    return torch.cat(rows).to(valid.device), torch.cat(cols).to(valid.device)


def view_contrastive_loss(top_down: torch.Tensor, bottom_up: torch.Tensor, valid: torch.Tensor,
                          config: ContrastiveConfig = ContrastiveConfig(),
                          generator: torch.Generator | None = None) -> torch.Tensor:
    """Margin loss between aligned feature tensors, negatives distance-weighted across the batch.

    top_down, bottom_up: B×C×(spatial…) unit-norm features (2D: B×C×H×W, 3D: B×C×Z×Y×X);
    valid: B×1×(spatial…) (where the target is observed and in bounds). Returns a scalar
    (0 with a zero gradient path if nothing is valid).
    """
    if top_down.shape != bottom_up.shape:
        raise ShapeError(f"top_down {tuple(top_down.shape)} and bottom_up {tuple(bottom_up.shape)} differ")
    B, C = top_down.shape[:2]
    top = top_down.reshape(B, C, -1)             # B×C×P
    bot = bottom_up.reshape(B, C, -1)            # B×C×P
    ok = valid.reshape(B, -1) > 0.5              # B×P
    rows, cols = sample_positions(ok, config.samples, generator)
    if rows.numel() < 2:  # a negative needs at least two pairs
        return (top_down.sum() + bottom_up.sum()) * 0.0
    # One label per (example, position): a position drawn twice (sampling with replacement, when an example
    # has fewer valid positions than samples) is the same pair, never its own negative.
    ids = rows * top.shape[2] + cols             # K
    if ids.unique().numel() < 2:  # a negative needs a second distinct pair
        return (top_down.sum() + bottom_up.sum()) * 0.0
    a = top[rows, :, cols].float()               # K×C
    b = bot[rows, :, cols].float()               # K×C
    emb = torch.stack([a, b], dim=1).reshape(-1, C)  # 2K×C, pairs interleaved (top, bottom, top, …)
    labels = ids.repeat_interleave(2)            # 2K
    negatives = sample_negatives(emb, labels, cutoff=config.cutoff,
                                 nonzero_loss_cutoff=config.nonzero_loss_cutoff, generator=generator)
    partner = torch.arange(emb.shape[0], device=emb.device) ^ 1  # index of the other half of each pair
    return margin_loss(emb, emb[partner], emb[negatives], beta=config.beta, margin=config.margin)
