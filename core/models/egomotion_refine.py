"""Sub-voxel refinement of an egomotion estimate: Gauss-Newton on dense feature-metric alignment.

Conventions (docs/conventions.md#poses): E = `ref0_T_ref1` (B×4×4); volumes B×C×Z×Y×X on one map grid
(the reference R in ref0, the query Q in ref1); voxel centres p in ref0 metres. Q_E(p) = Q(E⁻¹·p) is the
query warped into ref0 (trilinear, as core.geometry.resample.warp_rigid).

Model: if the truth is exp(δ)·E (δ = (ω rad axis-angle, t metres), a left update in ref0, as the coarse
scales of core.models.egomotion apply), then Q_E(p) = R(exp(δ)·p). Linearised at δ = 0 with
exp(δ)·p ≈ p + ω×p + t:

    Q_E(p) − R(p) ≈ J(p)·δ,   J(p) = [p × ∇R(p) | ∇R(p)]   (per channel: 1×6, ∇R per metre)

so one Gauss-Newton step is δ = (Σ w JᵀJ + λ·diag + ε)⁻¹ Σ w Jᵀ r with r = Q_E − R, then E ← exp(δ)·E.
J depends on the reference only (inverse-compositional: the Jacobian is computed once per call, each
iteration samples the ORIGINAL query once more at E⁻¹·p — never a warped volume again), and only the
voxels where J ≠ 0 are sampled (exact: the others add nothing; most of a sparse volume is empty).
∇R is the central difference of R along x, y, z (one-sided at the faces). w(p) is 1 where both the
voxel and its warped position lie at least `margin` voxels inside the grid (no zero padding enters r or ∇R),
times an optional per-voxel confidence B×1×Z×Y×X (e.g. learned), times a robust Cauchy weight on the
per-voxel residual norm when `robust_scale` > 0. Everything is differentiable (the solve is
`torch.linalg.solve`), so a loss on the refined pose trains the features that go in (as BA-Net / PixLoc).

What limits it, measured on the small preset's 8 moving-camera test pairs (0.5 m voxels; fixed volumes
from the truth, tests/benchmarks/bench_egomotion_precision.py --floors): with binary occupancy the optimum
is 0.0050 rad / 0.060 m off the truth (0.0034 / 0.061 even for frame 0's own points moved by the true
motion: quantisation); with area-weighted trilinear splats summed over the views 0.0031 / 0.058 (the
overlaps of the views double the density in seams that move with the rig); with their max over the
views 0.0012 / 0.026 — point-to-plane ICP on the same pairs: 0.0011 / 0.026. Interpolation alone biases
a smooth synthetic field by ~1 % of a small motion's rotation at this voxel size (unit tests).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import check_shape
from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref, ref_T_mem, voxel_centers_mem, voxel_centers_ref
from core.geometry.resample import check_volume_matches_grid, sample_volume_at
from core.precision import full_precision


def spatial_gradient(vol: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Central differences of B×C×Z×Y×X along (x, y, z), per metre (one-sided at the faces) -> B×C×3×Z×Y×X."""
    grads = []
    for dim in (4, 3, 2):  # x, y, z
        n = vol.shape[dim]
        if n < 2:
            grads.append(torch.zeros_like(vol))
            continue
        hi = torch.cat([vol.narrow(dim, 1, n - 1), vol.narrow(dim, n - 1, 1)], dim=dim)  # v[i+1] (clamped)
        lo = torch.cat([vol.narrow(dim, 0, 1), vol.narrow(dim, 0, n - 1)], dim=dim)      # v[i−1] (clamped)
        span = torch.full((n,), 2.0, dtype=vol.dtype, device=vol.device)
        span[0] = span[-1] = 1.0
        shape = [1] * vol.dim()
        shape[dim] = n
        grads.append((hi - lo) / (span.view(shape) * voxel_size))
    return torch.stack(grads, dim=2)


def interior_mask(grid: GridConfig, *, margin: int = 1, dtype=torch.float32, device=None) -> torch.Tensor:
    """1 on voxels at least `margin` voxels inside every face (all voxels of an axis thinner than
    2·margin + 1), else 0: Z×Y×X."""
    m = torch.ones(grid.Z, grid.Y, grid.X, dtype=dtype, device=device)
    for dim, n in enumerate(grid.shape_zyx):
        if n > 2 * margin:
            idx = torch.arange(n, device=device)
            keep = ((idx >= margin) & (idx < n - margin)).to(dtype)
            shape = [1, 1, 1]
            shape[dim] = n
            m = m * keep.view(shape)
    return m


def alignment_jacobian(reference: torch.Tensor, grid: GridConfig,
                       index: torch.Tensor | None = None) -> torch.Tensor:
    """J of the module doc for every voxel (or the voxels `index`, M flat indices) and channel:
    reference B×C×Z×Y×X -> B×C×N×6 (N = Z·Y·X) or B×C×M×6."""
    B, C = reference.shape[:2]
    grad = spatial_gradient(reference, grid.voxel_size).reshape(B, C, 3, -1).transpose(2, 3)  # B×C×N×3
    p = voxel_centers_ref(grid, dtype=reference.dtype, device=reference.device)  # N×3
    if index is not None:
        grad, p = grad[:, :, index], p[index]
    rot = torch.cross(p.expand_as(grad), grad, dim=-1)  # B×C×N×3: p × ∇R
    return torch.cat([rot, grad], dim=-1)  # B×C×N×6


@full_precision  # poses, sampling positions and the normal equations: float32 under bf16 autocast (core.precision)
def gauss_newton_refine(reference: torch.Tensor, query: torch.Tensor, estimate: torch.Tensor, grid: GridConfig,
                        *, iterations: int = 3, damping: float = 1e-3, confidence: torch.Tensor | None = None,
                        robust_scale: float = 0.0, max_step: tuple[float, float] | None = None,
                        margin: int = 1, query_confidence: torch.Tensor | None = None,
                        ) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Refine `ref0_T_ref1` by `iterations` Gauss-Newton steps (module doc).

    reference (ref0), query (ref1): B×C×Z×Y×X on `grid`; estimate: B×4×4; confidence: B×1×Z×Y×X (on the
    reference's voxels) or None; query_confidence: B×1×Z×Y×X on the query's voxels (warped with it) or
    None; damping: λ (Levenberg-Marquardt, relative to the Hessian's diagonal); max_step: (rad, m) clamp of
    each step's rotation and translation norms, or None; margin: voxels next to the faces left out.
    Returns (the refined B×4×4, the estimate after each iteration).
    """
    check_volume_matches_grid("reference", reference, grid)
    check_shape("query", query, tuple(reference.shape))
    B, C = reference.shape[:2]
    check_shape("estimate", estimate, (B, 4, 4))
    dtype, device = reference.dtype, reference.device
    N = grid.Z * grid.Y * grid.X
    base_w = interior_mask(grid, margin=margin, dtype=dtype, device=device).reshape(1, N).expand(B, N)
    if confidence is not None:
        check_shape("confidence", confidence, (B, 1, *grid.shape_zyx))
        base_w = base_w * confidence.reshape(B, N)
    if query_confidence is not None:
        check_shape("query_confidence", query_confidence, (B, 1, *grid.shape_zyx))
        query = torch.cat([query, query_confidence.to(dtype)], dim=1)  # warped together: one sampling
    # Only voxels where J ≠ 0 can move the solution (elsewhere they add 0 to H and to Jᵀr): keep those
    # (any example's), which is exact and skips the empty space of a sparse volume.
    # (J = 0 exactly where ∇R = 0, since its rotation part is p × ∇R.)
    grad = spatial_gradient(reference.detach(), grid.voxel_size)  # B×C×3×Z×Y×X
    active = ((grad != 0).flatten(1, 2).any(dim=1).reshape(B, N) & (base_w.detach() != 0)).any(dim=0)  # N
    index = active.nonzero().squeeze(1)  # M
    J, base_w = alignment_jacobian(reference, grid, index), base_w[:, index]  # B×C×M×6, B×M
    ref_flat = reference.reshape(B, C, N)[:, :, index]  # B×C×M
    # The active voxel centres in mem; their warped position must stay `margin` voxels inside the query's grid.
    centres = voxel_centers_mem(grid, dtype=dtype, device=device)[index]  # M×3
    lo = torch.tensor([margin if n > 2 * margin else 0 for n in (grid.X, grid.Y, grid.Z)], dtype=dtype,
                      device=device)
    hi = torch.tensor([grid.X - 1, grid.Y - 1, grid.Z - 1], dtype=dtype, device=device) - lo
    mem = mem_T_ref(grid, dtype=dtype, device=device).expand(B, 4, 4)
    ref_from_mem = ref_T_mem(grid, dtype=dtype, device=device).expand(B, 4, 4)
    eye = torch.eye(6, dtype=dtype, device=device)
    E = estimate
    history = []
    for _ in range(iterations):
        xyz = se3.apply(mem @ se3.invert(E) @ ref_from_mem, centres.expand(B, -1, 3))  # B×M×3 in the query
        warped = sample_volume_at(query, xyz.reshape(B, 1, 1, -1, 3)).reshape(B, query.shape[1], -1)  # B×C(+1)×M
        inside = ((xyz.detach() >= lo - 1e-4) & (xyz.detach() <= hi + 1e-4)).all(-1)  # B×M
        w = base_w * inside.to(dtype)  # B×M
        if query_confidence is not None:
            warped, w = warped[:, :C], w * warped[:, C]
        r = warped - ref_flat  # B×C×M
        if robust_scale > 0:
            w = w / (1.0 + r.square().sum(1) / robust_scale ** 2)
        Jw = J * w[:, None, :, None]  # B×C×M×6
        H = torch.einsum("bcni,bcnj->bij", Jw, J)  # B×6×6
        g = torch.einsum("bcni,bcn->bi", Jw, r)  # B×6
        diag = torch.diagonal(H, dim1=1, dim2=2)  # B×6
        # LM damping, and a tiny ridge so that an empty volume (H = 0) gives δ = 0 instead of a singular solve
        A = H + damping * torch.diag_embed(diag) + 1e-6 * (diag.mean(1, keepdim=True)[..., None] + 1e-3) * eye
        delta = torch.linalg.solve(A, g.unsqueeze(-1)).squeeze(-1)  # B×6 (ω, t)
        if max_step is not None:
            delta = torch.cat([clamp_norm(delta[:, :3], max_step[0]), clamp_norm(delta[:, 3:], max_step[1])], 1)
        E = se3.from_rt(se3.axis_angle_to_matrix(delta[:, :3]), delta[:, 3:]) @ E
        history.append(E)
    return E, history


def clamp_norm(v: torch.Tensor, limit: float) -> torch.Tensor:
    """v …×k scaled down so that its norm over the last axis is at most `limit` (unchanged when it is)."""
    n = v.norm(dim=-1, keepdim=True)
    return v * torch.clamp(limit / n.clamp_min(1e-12), max=1.0)


def gaussian_blur3d(vol: torch.Tensor, sigma_vox: float) -> torch.Tensor:
    """Separable Gaussian blur of B×C×Z×Y×X (σ in voxels, radius ⌈2σ⌉, zero padding); σ ≤ 0: unchanged."""
    if sigma_vox <= 0:
        return vol
    r = max(1, int(round(2 * sigma_vox)))
    x = torch.arange(-r, r + 1, dtype=vol.dtype, device=vol.device)
    k = torch.exp(-0.5 * (x / sigma_vox) ** 2)
    k = k / k.sum()
    B, C = vol.shape[:2]
    out = vol.reshape(B * C, 1, *vol.shape[2:])
    for dim in (2, 3, 4):  # z, y, x
        shape = [1, 1, 1, 1, 1]
        shape[dim] = 2 * r + 1
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (4 - dim)] = pad[2 * (4 - dim) + 1] = r
        out = F.conv3d(F.pad(out, pad), k.view(shape))
    return out.reshape(vol.shape)


# (blur σ in voxels, Cauchy robust scale in occupancy units, Gauss-Newton iterations), coarse to fine.
# Chosen on the small preset's 8 moving-camera test pairs of /work/main/out/diag/test (splatted
# occupancy, from the identity; so those pairs flatter it: README "Egomotion" has fresh pairs too):
# σ 0.7 alone needs 8 iterations to come in from 0.8 m (4: 0.14 m), σ 1.5 widens the basin and then
# σ 0.7 is the sharpest that stays stable (σ 0: 0.15 m from the identity, σ 1.5 alone biased to 0.07 m).
DEFAULT_LEVELS = ((1.5, 0.2, 2), (0.7, 0.1, 3))
# The levels in eval mode (inference, evaluation, the held-out criterion): the same with the fine level run
# to convergence. Training backpropagates through every iteration, so it keeps the short schedule (as RAFT
# trains with fewer update iterations than it tests with). Measured (session 15, small, 32 held-out
# moving-camera pairs of `data generate --seed 7 --moving-ego on`): 3 -> 6 iterations at σ 0.7 lowered the
# mean rotation error of every model tried (the benchmark's three egomotion stages 0.096 / 0.110 / 0.099 ->
# 0.091 / 0.100 / 0.091 deg, three 1000-step models 0.093 / 0.095 / 0.095 -> 0.089 / 0.093 / 0.091) and
# their translation error by 3-7 %; 10 or 20 iterations gave the same as 6 (converged). Training with 6 too
# (seed 0, 1000 steps) gave no better a module (0.090 deg / 0.029 m against 0.089 / 0.024).
DEFAULT_INFERENCE_LEVELS = ((1.5, 0.2, 2), (0.7, 0.1, 6))
GAIN_INIT = 0.05


def _checked_levels(levels, name: str) -> tuple[tuple[float, float, int], ...]:
    checked = tuple((float(s), float(r), int(n)) for s, r, n in levels)
    if not checked or sum(n for _, _, n in checked) < 1 or min(n for _, _, n in checked) < 0:
        raise ValueError(f"FeatureMetricRefiner: {name} need at least one iteration, got {levels}")
    return checked


class FeatureMetricRefiner(nn.Module):
    """The egomotion module's sub-voxel stage: `gauss_newton_refine` on the full grid, per level of
    DEFAULT_LEVELS-like `levels` in training mode and `inference_levels` in eval mode, over the module's own
    volumes:

    - features: the input volumes' occupancy channel (continuous when the module reads splatted
      occupancy, core.models.input_volume) and `learned_channels` 1×1×1 projections of the module's
      encoder features, multiplied by a learned gain that starts at GAIN_INIT (small: they enter the
      Gauss-Newton system squared, so at 0.05 they weigh ~0.25 % of the occupancy; not 0, where the
      gradient w.r.t. the gain vanishes); each level blurs them by its σ;
    - per-voxel confidence 2·sigmoid(1×1×1 conv of the encoder features), starting at exactly 1, on the
      reference's voxels times the query's (warped with it), times the robust weight.
    Untrained (and without learned channels, the default) it is plain geometric dense alignment of the two
    occupancy volumes; training (the pose loss on its output, backpropagated through the Gauss-Newton
    solves) learns where the alignment should trust the volumes, as BA-Net / PixLoc. Measured (small, 8
    moving-camera test pairs, 2 seeds × 300 steps with 4 learned channels): the learned confidence takes
    t from 0.028 to 0.025 m (rotation 0.0013 rad either way); the learned channels' gain stayed near 0
    (0.045, 0.007) and silencing them changes nothing (≤ 0.0002 m), while they make every voxel active
    and cost ~60 ms per pair on one thread — so they are off (`learned_channels=0`). Cost with them off:
    ~25-30 ms per pair at small on one thread (on top of the coarse scales' ~90 ms).
    """

    def __init__(self, *, feature_dim: int, learned_channels: int = 0,
                 levels: tuple[tuple[float, float, int], ...] = DEFAULT_LEVELS,
                 inference_levels: tuple[tuple[float, float, int], ...] = DEFAULT_INFERENCE_LEVELS,
                 damping: float = 1e-3, max_step: tuple[float, float] = (0.05, 1.0)) -> None:
        super().__init__()
        self.levels = _checked_levels(levels, "levels")
        # Bundles saved before inference_levels existed load with the default: their fine level then runs
        # to convergence at inference too (it lowered every such module's errors, DEFAULT_INFERENCE_LEVELS).
        self.inference_levels = _checked_levels(inference_levels, "inference_levels")
        self.learned_channels, self.damping = int(learned_channels), float(damping)
        self.max_step = (float(max_step[0]), float(max_step[1]))
        self.project = nn.Conv3d(feature_dim, self.learned_channels, 1) if self.learned_channels > 0 else None
        self.gain = nn.Parameter(torch.tensor(GAIN_INIT))
        self.confidence = nn.Conv3d(feature_dim, 1, 1)
        nn.init.zeros_(self.confidence.weight)
        nn.init.zeros_(self.confidence.bias)

    def config(self) -> dict:
        return {"learned_channels": self.learned_channels, "levels": [list(l) for l in self.levels],
                "inference_levels": [list(l) for l in self.inference_levels],
                "damping": self.damping, "max_step": list(self.max_step)}

    def features(self, volume: torch.Tensor, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(alignment features B×(1+L)×Z×Y×X, confidence B×1×Z×Y×X) of one frame."""
        chans = [volume[:, :1]]
        if self.project is not None:
            chans.append(self.gain * self.project(feat))
        return torch.cat(chans, dim=1), 2.0 * torch.sigmoid(self.confidence(feat))

    def forward(self, reference_input: torch.Tensor, query_input: torch.Tensor, reference_feat: torch.Tensor,
                query_feat: torch.Tensor, estimate: torch.Tensor, grid: GridConfig) -> tuple[torch.Tensor, list]:
        """Input volumes B×Cin×Z×Y×X, encoder features B×F×Z×Y×X (ref0, ref1), estimate B×4×4 ->
        (refined B×4×4, the estimate after every iteration)."""
        fr, cr = self.features(reference_input, reference_feat)
        fq, cq = self.features(query_input, query_feat)
        E, history = estimate, []
        for sigma, robust, iterations in (self.levels if self.training else self.inference_levels):
            E, steps = gauss_newton_refine(gaussian_blur3d(fr, sigma), gaussian_blur3d(fq, sigma), E, grid,
                                           iterations=iterations, damping=self.damping, confidence=cr,
                                           query_confidence=cq, robust_scale=robust, max_step=self.max_step)
            history += steps
        return E, history
