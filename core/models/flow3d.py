"""3D imagination flow: PWC-style coarse-to-fine 3D flow between two egomotion-stabilised feature maps.

Conventions (docs/conventions.md#3d-flow): feature volumes B×F×Z×Y×X in the SAME frame (`ref` at t, the second map
already registered into it); flow volumes B×3×Z×Y×X, channels (x, y, z), voxel units, from t to t+1:
    f1(p + flow(p)) ≈ f0(p).

Per level l = finest..finest+levels-1 (coarsest first; level l has 2^l-times coarser voxels, from
average pooling; as in PWC-Net, the finest decoder runs at half resolution by default (`finest=1`) and
its flow is upsampled to the grid, 8× cheaper than a full-resolution decoder; `finest=0` runs the last
decoder on the grid itself):
1. upsample the coarser level's flow (trilinear, values scaled by the size ratio per axis);
2. warp the level's second pyramid volume by it (backward warp `warp_flow`; PWC's incremental warping);
3. local 3D cost volume (cross-correlation within ±radius voxels) between the first volume and the warp;
   `unit_cost=True`: of unit-length features, i.e. cosines in [-1, 1] (the per-channel mean of raw
   features was ~0.01 at init and the decoders learned nothing from it);
4. (`soft_argmax=True`) add the soft-argmax of the costs (Σ_d softmax(β·cost)_d · d, β learned) to the
   upsampled flow: a correlator that works before any training;
5. a small 3D conv decoder on [cost, first volume, upsampled flow] predicts a residual; flow = up + res.
   `cost_channels=k > 0`: the D costs pass a learned 1×1×1 conv to k channels first, so a wide window does
   not widen the decoder (see `__init__`).
`refine=True` (with `finest=1`): one more step on the grid without a decoder: warp by the upsampled flow,
cosine costs, flow = up + soft-argmax. Why: at 1 m voxels (tiny) a car is ~4×2×2 voxels and moves
~0.4-1.6 voxels; the half-resolution decoders blur it into the background, and a full-resolution decoder
costs ~6× the whole module (tiny, CPU); the decoder-free correlator step recovers the object's
displacement at the grid's resolution for the price of one cost volume. Measured (tiny, 150 self-supervised
steps, 8 held-out records, moving voxels' L1 EPE vs zero motion 1.156 / static voxels' L1 EPE):
refine (β 10) 0.807 / 0.43, full-resolution decoder + soft-argmax at every level 0.803 / 0.44, no
correlator 1.15-1.16 / ~0.01. The soft-argmax spreads sub-voxel noise onto static voxels near surfaces;
a sharper β and a small learned bonus `zero_bias` of d = 0 trade some of the moving accuracy for much
less of it: β 30 + bonus 0.05: 0.861 / 0.20 (bonus 0.2: 0.993 / 0.15) — FlowTask's defaults.
At small (0.5 m voxels, true motions up to 3 voxels along x and z) the step's window matters most: with the
decoders at ±1, a ±3/±1/±3 grid step (`refine_radius`) gives what ±3 at every level gives (over matching-
trained features, seed 0, 16 test records: raw moving EPE 0.82 × zero motion both). `refine_aggregate` then
averages each displacement's cost over a box around each voxel before the soft-argmax (`aggregate_costs`):
trained with ±1 boxes, 0.67 × (one seed; three in docs/findings.md).
The pyramid comes from a small learned 3D conv on the input, then average pooling, so the coarse voxels
of level l are exactly the 2^l blocks of the grid and flow upsampling needs no offset.
The last conv of each decoder starts at zero: an untrained module without the correlator steps predicts
zero motion.

Inputs (`inputs`, recorded in `config()` so a pipeline knows what to feed): "features" = the mapper's
latent maps (the paper), "volume" = the 4-channel fused input volumes (occupancy + RGB,
core.models.egomotion_inputs.fused_input_volume) of t and of t+1 re-lifted into ref_t. Why "volume":
on tiny (F = 8, mapper pretrained 150 steps) the best integer shift of the map matched the true motion
of 2 of 17 held-out moving cars (8 of 78 with the training records; the best shift was almost always 0),
that of the input volume 12 of 17 — the maps do not carry the object motion, so no flow over them can.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import check_shape
from core.geometry.resample import warp_flow
from core.models.cost_volume import cross_correlation_3d, soft_argmax_displacement
from core.models.normalize import l2_normalize_channels
from core.models.conv3d import Conv3d


FLOW_INPUTS = ("features", "volume")
VOLUME_CHANNELS = 4  # core.models.egomotion_inputs.fused_input_volume: occupancy + RGB


def upsample_flow(flow: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """flow B×3×z×y×x (voxels of the coarse level) -> B×3×Z×Y×X at `size`, values in fine voxels.

    Each channel is scaled by its own axis ratio (x by X/x, y by Y/y, z by Z/z).
    """
    _, _, z, y, x = flow.shape
    Z, Y, X = size
    up = F.interpolate(flow, size=size, mode="trilinear", align_corners=False)  # B×3×Z×Y×X
    scale = torch.tensor([X / x, Y / y, Z / z], dtype=flow.dtype, device=flow.device).view(1, 3, 1, 1, 1)
    return up * scale


def downsample_flow(flow: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """flow B×3×Z×Y×X -> B×3×z×y×x (average over each coarse voxel, values in coarse voxels)."""
    Z, Y, X = flow.shape[-3:]
    z, y, x = size
    down = F.adaptive_avg_pool3d(flow, size)  # B×3×z×y×x
    scale = torch.tensor([x / X, y / Y, z / Z], dtype=flow.dtype, device=flow.device).view(1, 3, 1, 1, 1)
    return down * scale


def pool_pyramid(c: torch.Tensor, sizes: list[tuple[int, int, int]]) -> list[torch.Tensor]:
    """c: B×C×Z×Y×X at sizes[0] -> [B×C×z_l×y_l×x_l per size], the block means of c (adaptive pooling).
    Where a level exactly halves the one below on every axis it is that level's 2×2×2 mean (the same
    means up to float rounding, and cheaper: the small grid's pyramid took ~3 ms instead of ~6 ms)."""
    pyramid = [c]
    for size in sizes[1:]:
        below = pyramid[-1]
        if all(n == 2 * m for n, m in zip(below.shape[-3:], size)):
            pyramid.append(F.avg_pool3d(below, 2))  # B×C×z×y×x
        else:
            pyramid.append(F.adaptive_avg_pool3d(c, size))  # B×C×z×y×x
    return pyramid


def level_sizes(size: tuple[int, int, int], levels: int) -> list[tuple[int, int, int]]:
    """Sizes of the pyramid, finest first: each level halves every axis (ceil), never below 1."""
    sizes = [tuple(size)]
    for _ in range(levels - 1):
        sizes.append(tuple(max(1, (n + 1) // 2) for n in sizes[-1]))
    return sizes


def aggregate_costs(cost: torch.Tensor, half_widths: tuple[int, int, int]) -> torch.Tensor:
    """cost B×D×Z×Y×X -> B×D×Z×Y×X, each displacement's cost averaged over the box of ±(ax, ay, az) voxels
    around each voxel, the box clipped to the grid (the mean of the voxels inside it).

    Why: one voxel's cosines against its ±3 neighbours rarely single out its true shift (measured on the small
    test records: the best shift of a moving voxel's feature is the true one for ~25 % of them), but an
    object moves rigidly, so the voxels around it share the shift: summing their costs is stereo's cost
    aggregation, a parameter-free rigidity prior. As three 1D means (the box's count of voxels inside the grid
    is the product of the per-axis counts, so it equals the 3D box mean); see `_BoxMean` for the backward.
    """
    half_widths = tuple(int(a) for a in half_widths)
    if not any(half_widths):
        return cost
    return _BoxMean.apply(cost, half_widths)


def _box_axes(half_widths: tuple[int, int, int]):
    """(dim of a B×D×Z×Y×X tensor, half-width) per axis with a box: z, y, x."""
    return [(dim, a) for dim, a in ((2, half_widths[2]), (3, half_widths[1]), (4, half_widths[0])) if a > 0]


def _box_sum_axis(x: torch.Tensor, dim: int, a: int) -> torch.Tensor:
    """A new tensor: x summed over ±a along `dim`, zero outside (a shifted view added in place per offset)."""
    n = x.shape[dim]
    total = x.clone()
    for k in range(1, min(a, n - 1) + 1):
        total.narrow(dim, k, n - k).add_(x.narrow(dim, 0, n - k))  # the voxel k before
        total.narrow(dim, 0, n - k).add_(x.narrow(dim, k, n - k))  # the voxel k after
    return total


def _box_counts(x: torch.Tensor, dim: int, a: int) -> torch.Tensor:
    """Voxels of each clipped ±a box along `dim`, shaped to broadcast against x."""
    n = x.shape[dim]
    index = torch.arange(n, device=x.device)
    inside = (index + a).clamp(max=n - 1) - (index - a).clamp(min=0) + 1
    shape = [1] * x.dim()
    shape[dim] = n
    return inside.to(x.dtype).view(shape)


_BOX_CHUNK = 4  # displacements per box-mean pass (why: `_box_mean`)


def _box_mean(x: torch.Tensor, half_widths: tuple[int, int, int], *, adjoint: bool) -> torch.Tensor:
    """x B×D×Z×Y×X -> the clipped box mean (adjoint=False) or its transpose (adjoint=True), B×D×Z×Y×X.

    Per axis the mean is M = diag(1/count)·S with S the zero-padded box sum; S is symmetric, so Mᵀ =
    S·diag(1/count) (the axes act on separate dimensions and commute). Computed a few displacements at a
    time: each pass's temporaries (~2 MB at the small grid) are then reused by the allocator instead of
    fresh ~80 MB blocks paged in per axis (at D 147: 109 ms against 185 ms per call, one thread)."""
    out = torch.empty_like(x)
    for lo in range(0, x.shape[1], _BOX_CHUNK):
        part = x[:, lo:lo + _BOX_CHUNK]  # B×k×Z×Y×X
        for dim, a in _box_axes(half_widths):
            counts = _box_counts(part, dim, a)
            part = _box_sum_axis(part / counts, dim, a) if adjoint else _box_sum_axis(part, dim, a).div_(counts)
        out[:, lo:lo + _BOX_CHUNK] = part
    return out


class _BoxMean(torch.autograd.Function):
    """The clipped box mean with a hand-written backward (its transpose, see `_box_mean`).

    Why: autograd through shifted slices of a padded copy allocates and zero-fills a whole B×D×Z×Y×X gradient
    per slice (D 147 at the recipe's ±3/±1/±3 grid step: ~80 MB each, 9 of them per pass)."""

    @staticmethod
    def forward(ctx, cost: torch.Tensor, half_widths: tuple[int, int, int]) -> torch.Tensor:
        ctx.half_widths = half_widths
        return _box_mean(cost, half_widths, adjoint=False)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        return _box_mean(grad, ctx.half_widths, adjoint=True), None


class Flow3D(nn.Module):
    """(f0, f1): B×F×Z×Y×X each -> flow B×3×Z×Y×X (plus the per-level flows, coarse to fine)."""

    def __init__(self, *, in_channels: int = 32, channels: int = 16, levels: int = 3,
                 radius: tuple[int, int, int] = (1, 1, 1), hidden: int = 32, finest: int = 1,
                 unit_cost: bool = False, soft_argmax: bool = False, beta: float = 10.0,
                 refine: bool = False, inputs: str = "features", zero_bias: float = 0.0,
                 cost_channels: int = 0, refine_radius: tuple[int, int, int] | None = None,
                 refine_aggregate: tuple[int, int, int] = (0, 0, 0)) -> None:
        super().__init__()
        self.zero_bias = float(zero_bias)
        if inputs not in FLOW_INPUTS:
            raise ValueError(f"Flow3D: inputs must be one of {FLOW_INPUTS}, got {inputs!r}")
        if inputs == "volume" and in_channels != VOLUME_CHANNELS:
            raise ValueError(f"Flow3D: inputs='volume' takes {VOLUME_CHANNELS} channels, got in_channels={in_channels}")
        self.inputs = inputs
        self.unit_cost, self.soft_argmax, self.beta = bool(unit_cost), bool(soft_argmax), float(beta)
        self.refine = bool(refine)
        if self.soft_argmax or self.refine:  # only then (modules saved without them keep loading)
            # β of each level's soft-argmax (decoder levels, then the grid refinement), learned in log space
            self.log_beta = nn.Parameter(torch.full((levels + 1,), float(beta)).log())
        if self.refine:
            # cosine bonus of d = 0 in the refinement's soft-argmax, learned (why: see module doc)
            self.refine_zero_bias = nn.Parameter(torch.tensor(float(zero_bias)))
        if finest not in (0, 1):
            raise ValueError(f"Flow3D: finest must be 0 (grid) or 1 (half resolution), got {finest}")
        self.finest = int(finest)
        self.in_channels, self.channels, self.levels, self.hidden = in_channels, channels, levels, hidden
        self.radius = tuple(int(r) for r in radius)
        # The grid refinement's window (None: `radius`). Why separate: its cost volume is on the full grid,
        # 8× the voxels of the finest decoder's, and it only corrects the upsampled flow by a voxel or so;
        # at ±3/±1/±3 it took 68 of the module's 215 ms (small, 1 thread) against 10 ms at ±1.
        self.refine_radius = self.radius if refine_radius is None else tuple(int(r) for r in refine_radius)
        if len(self.refine_radius) != 3 or min(self.refine_radius) < 0:
            raise ValueError(f"Flow3D: refine_radius must be three non-negative ints, got {refine_radius}")
        # Half-widths (x, y, z) of the box over which the grid step averages each displacement's cost before
        # its soft-argmax ((0, 0, 0): none): stereo's cost aggregation. See `aggregate_costs` for why.
        self.refine_aggregate = tuple(int(a) for a in refine_aggregate)
        if len(self.refine_aggregate) != 3 or min(self.refine_aggregate) < 0:
            raise ValueError(f"Flow3D: refine_aggregate must be three non-negative ints, got {refine_aggregate}")
        self.features = nn.Sequential(
            Conv3d(in_channels, channels, 3, padding=1), nn.LeakyReLU(0.1),
            Conv3d(channels, channels, 3, padding=1))
        n_disp = (2 * self.radius[0] + 1) * (2 * self.radius[1] + 1) * (2 * self.radius[2] + 1)
        if cost_channels < 0:
            raise ValueError(f"Flow3D: cost_channels must be >= 0 (0: no squeeze), got {cost_channels}")
        self.cost_channels = int(cost_channels)
        if self.cost_channels:
            # Per level, a 1×1×1 conv squeezes the D window costs to `cost_channels` before the decoder.
            # Why: the decoder's first 3×3×3 conv dominates the module's cost and grows with D (75 at ±2/±1/±2,
            # 147 at ±3/±1/±3); the squeeze costs D·k per voxel instead of 27·D·hidden.
            self.cost_squeeze = nn.ModuleList(
                nn.Sequential(Conv3d(n_disp, self.cost_channels, 1), nn.LeakyReLU(0.1)) for _ in range(levels))
        decoder_cost = self.cost_channels or n_disp
        self.decoders = nn.ModuleList()
        for _ in range(levels):
            dec = nn.Sequential(
                Conv3d(decoder_cost + channels + 3, hidden, 3, padding=1), nn.LeakyReLU(0.1),
                Conv3d(hidden, hidden, 3, padding=1), nn.LeakyReLU(0.1),
                Conv3d(hidden, 3, 3, padding=1))
            nn.init.zeros_(dec[-1].weight)
            nn.init.zeros_(dec[-1].bias)
            self.decoders.append(dec)

    def pick_inputs(self, *, features: tuple[torch.Tensor, torch.Tensor],
                    volumes: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The pair this module compares: (f0, f1) maps B×F×Z×Y×X or (v0, v1) input volumes B×4×Z×Y×X,
        both stabilised into ref_t, by `self.inputs`."""
        return features if self.inputs == "features" else volumes

    def config(self) -> dict:
        return {"in_channels": self.in_channels, "channels": self.channels, "levels": self.levels,
                "radius": list(self.radius), "hidden": self.hidden, "finest": self.finest,
                "unit_cost": self.unit_cost, "soft_argmax": self.soft_argmax, "beta": self.beta,
                "refine": self.refine, "inputs": self.inputs, "zero_bias": self.zero_bias,
                "cost_channels": self.cost_channels, "refine_radius": list(self.refine_radius),
                "refine_aggregate": list(self.refine_aggregate)}

    def encode(self, volume: torch.Tensor) -> torch.Tensor:
        """The learned pyramid input of one map or volume: B×Cin×Z×Y×X -> B×C×Z×Y×X. Per example (no
        normalisation across the batch), so a stream computes frame t's once, as the next pair's `encoded0`."""
        check_shape("volume", volume, (None, self.in_channels, None, None, None))
        return self.features(volume)

    def forward(self, f0: torch.Tensor, f1: torch.Tensor, *,
                encoded0: torch.Tensor | None = None) -> dict[str, torch.Tensor | list[torch.Tensor]]:
        """f0, f1: B×F×Z×Y×X (same frame) -> {"flow": B×3×Z×Y×X (grid resolution),
        "levels": [B×3×z_l×y_l×x_l] per decoder, coarse first, in each level's own voxel units}.
        encoded0: `encode(f0)` when the caller kept it (B×C×Z×Y×X), else computed here."""
        check_shape("f0", f0, (None, self.in_channels, None, None, None))
        check_shape("f1", f1, tuple(f0.shape))
        B = f0.shape[0]
        if encoded0 is None:
            c = self.features(torch.cat([f0, f1], dim=0))  # 2B×C×Z×Y×X
        else:
            check_shape("encoded0", encoded0, (B, self.channels, *f0.shape[-3:]))
            c = torch.cat([encoded0, self.features(f1)], dim=0)  # 2B×C×Z×Y×X
        sizes = level_sizes(tuple(f0.shape[-3:]), self.finest + self.levels)  # grid, then coarser
        pyramid = pool_pyramid(c, sizes)  # finest first
        flow = None
        per_level = []
        for level in reversed(range(self.finest, self.finest + self.levels)):
            c0, c1 = pyramid[level][:B], pyramid[level][B:]  # B×C×z×y×x each
            if flow is None:
                up = c0.new_zeros(B, 3, *sizes[level])
                warped = c1
            else:
                up = upsample_flow(flow, sizes[level])  # B×3×z×y×x
                warped = warp_flow(c1, up)
            if self.unit_cost:
                raw = cross_correlation_3d(l2_normalize_channels(c0), l2_normalize_channels(warped), self.radius)  # cosines
            else:
                raw = cross_correlation_3d(c0, warped, self.radius, normalize=True)
            if self.cost_channels:
                cost = self.cost_squeeze[level - self.finest](raw)  # B×k×z×y×x
            else:
                cost = F.leaky_relu(raw, 0.1)  # B×D×z×y×x
            if self.soft_argmax:
                up = up + soft_argmax_displacement(raw, self.radius, self.log_beta[level - self.finest].exp())
            flow = up + self.decoders[level - self.finest](torch.cat([cost, c0, up], dim=1))  # B×3×z×y×x
            per_level.append(flow)
        if self.refine and self.finest > 0:
            up = upsample_flow(flow, sizes[0])  # B×3×Z×Y×X
            c0, c1 = pyramid[0][:B], pyramid[0][B:]  # B×C×Z×Y×X each
            raw = cross_correlation_3d(l2_normalize_channels(c0), l2_normalize_channels(warp_flow(c1, up)),
                                       self.refine_radius)
            centre = raw.shape[1] // 2  # d = 0 (z-major order, see core.models.cost_volume.displacements)
            raw[:, centre] += self.refine_zero_bias  # in place: raw is a fresh stack no backward reads
            raw = aggregate_costs(raw, self.refine_aggregate)  # B×D×Z×Y×X
            flow = up + soft_argmax_displacement(raw, self.refine_radius, self.log_beta[-1].exp())  # B×3×Z×Y×X
            per_level.append(flow)
        return {"flow": upsample_flow(flow, sizes[0]), "levels": per_level}
