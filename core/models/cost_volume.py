"""3D cross-correlation cost volume: the matching score of every voxel against nearby displaced voxels.

Conventions (docs/conventions.md#3d-flow): volumes are B×C×Z×Y×X; displacements are (x, y, z) in voxels.

cost[b, d, z, y, x] = Σ_c f0[b, c, z, y, x] · f1[b, c, z + dz, y + dy, x + dx] / C_norm
for every displacement d = (dx, dy, dz) with |dx| ≤ rx, |dy| ≤ ry, |dz| ≤ rz; f1 is zero outside the
volume. C_norm = 1 (`normalize=False`, the plain dot product: cosine similarity for unit features) or C.
Displacements are ordered z-major, then y, then x (see `displacements`), so d = 0 sits in the middle.
The paper used a custom CUDA kernel; a loop over the (2r+1)³ shifted slices of a padded f1 is
memory-lean (no B×D×C×Z×Y×X intermediate) and fast enough for the radii used here.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from core.errors import ShapeError, check_shape
from core.precision import full_precision


def displacements(radius: tuple[int, int, int], *, device=None, dtype=torch.float32) -> torch.Tensor:
    """All integer displacements within radius (rx, ry, rz): D×3 in (x, y, z), z-major order."""
    rx, ry, rz = radius
    dz, dy, dx = torch.meshgrid(torch.arange(-rz, rz + 1), torch.arange(-ry, ry + 1),
                                torch.arange(-rx, rx + 1), indexing="ij")
    return torch.stack([dx, dy, dz], dim=-1).reshape(-1, 3).to(device=device, dtype=dtype)  # D×3


def cross_correlation_3d(f0: torch.Tensor, f1: torch.Tensor, radius: tuple[int, int, int], *,
                         normalize: bool = False) -> torch.Tensor:
    """f0, f1: B×C×Z×Y×X; radius (rx, ry, rz) voxels -> cost B×D×Z×Y×X, D = Π(2r+1)."""
    check_shape("f0", f0, (None, None, None, None, None))
    check_shape("f1", f1, tuple(f0.shape))
    radius = tuple(int(r) for r in radius)
    if len(radius) != 3 or min(radius) < 0:
        raise ShapeError(f"cross_correlation_3d: radius must be three non-negative ints, got {radius}")
    cost = _CrossCorrelation3D.apply(f0, f1, radius)  # B×D×Z×Y×X
    return cost / f0.shape[1] if normalize else cost


def _shifts(radius: tuple[int, int, int], size: tuple[int, int, int]):
    """(index of d, slices of the padded f1 that displacement d reads), in `displacements` order."""
    rx, ry, rz = radius
    Z, Y, X = size
    i = 0
    for dz in range(2 * rz + 1):
        for dy in range(2 * ry + 1):
            for dx in range(2 * rx + 1):
                yield i, (slice(None), slice(None), slice(dz, dz + Z), slice(dy, dy + Y), slice(dx, dx + X))
                i += 1


_TILE_BYTES = 1 << 20  # CPU: z-slabs of about this many bytes of one B×C×z×Y×X operand (why: `_z_tile`)


def _z_tile(volume: torch.Tensor) -> int:
    """z-slices per tile of the displacement loops: all of Z on an accelerator (one kernel per displacement);
    on CPU a slab of ~1 MB, so that the D displacements reuse it from cache instead of streaming the whole
    B×C×Z×Y×X operand from memory D times (small grid, C 16, ±3/±1/±3: forward 322 -> 200 ms, backward
    493 -> 219 ms, one thread)."""
    B, C, Z, Y, X = volume.shape
    if volume.device.type != "cpu":
        return Z
    return max(1, min(Z, _TILE_BYTES // max(1, B * C * Y * X * volume.element_size())))


class _CrossCorrelation3D(torch.autograd.Function):
    """The cost volume with a hand-written backward.

    Why: autograd through D shifted slices keeps, per displacement, a slice backward that allocates and
    zero-fills a whole padded B×C×… gradient and copies into it, plus a fresh product per displacement in
    each direction. At the flow grid step (small preset, B 2, C 16, 64×16×64, ±3/±1/±3: D 147) that was
    most of a 3.3 s training step. Here each direction reuses one product buffer and accumulates into one
    gradient in place: grad_f0 = Σ_d g_d · f1(p + d), grad_f1(q) = Σ_d g_d(q − d) · f0(q − d). Every loop
    runs over z-tiles (`_z_tile`), displacements inside; each output element still sums its displacements
    in `displacements` order with the same products, so the results equal the untiled loops bit for bit.
    The same sums as autograd's, in another order (tests/unit/egomotion/test_cost_volume.py checks both
    against autograd through the plain loop)."""

    @staticmethod
    def forward(ctx, f0: torch.Tensor, f1: torch.Tensor, radius: tuple[int, int, int]) -> torch.Tensor:
        rx, ry, rz = radius
        B, C, Z, Y, X = f0.shape
        dtype = torch.promote_types(f0.dtype, f1.dtype)  # mixed precision inputs: the wider (autograd casts back)
        f0 = f0.to(dtype)
        padded = F.pad(f1.to(dtype), (rx, rx, ry, ry, rz, rz))  # B×C×(Z+2rz)×(Y+2ry)×(X+2rx)
        D = (2 * rx + 1) * (2 * ry + 1) * (2 * rz + 1)
        cost = f0.new_empty(B, D, Z, Y, X)
        tile = _z_tile(f0)
        product = f0.new_empty(B, C, tile, Y, X)  # reused by every displacement and tile
        for z0 in range(0, Z, tile):
            z1 = min(z0 + tile, Z)
            part, out = f0[:, :, z0:z1], product[:, :, :z1 - z0]  # B×C×n×Y×X
            for i, (_, _, sz, sy, sx) in _shifts(radius, (Z, Y, X)):
                torch.mul(part, padded[:, :, sz.start + z0:sz.start + z1, sy, sx], out=out)
                torch.sum(out, dim=1, out=cost[:, i, z0:z1])  # B×n×Y×X
        ctx.save_for_backward(f0, padded)
        ctx.radius = radius
        return cost

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_cost: torch.Tensor):
        f0, padded = ctx.saved_tensors
        rx, ry, rz = ctx.radius
        Z, Y, X = f0.shape[-3:]
        tile = _z_tile(f0)
        need_f0, need_f1 = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_f0 = torch.zeros_like(f0) if need_f0 else None  # B×C×Z×Y×X
        grad_padded = torch.zeros_like(padded) if need_f1 else None  # B×C×(Z+2rz)×(Y+2ry)×(X+2rx)
        if need_f0:  # tiles of p: grad_f0(p) += g_d(p) · f1(p + d)
            for z0 in range(0, Z, tile):
                z1 = min(z0 + tile, Z)
                acc = grad_f0[:, :, z0:z1]  # B×C×n×Y×X
                for i, (_, _, sz, sy, sx) in _shifts(ctx.radius, (Z, Y, X)):
                    acc.addcmul_(grad_cost[:, i:i + 1, z0:z1], padded[:, :, sz.start + z0:sz.start + z1, sy, sx])
        if need_f1:  # tiles of the padded q = p + d: grad_f1(q) += g_d(q − d) · f0(q − d)
            for q0 in range(0, Z + 2 * rz, tile):
                q1 = min(q0 + tile, Z + 2 * rz)
                for i, (_, _, sz, sy, sx) in _shifts(ctx.radius, (Z, Y, X)):
                    p0, p1 = max(q0 - sz.start, 0), min(q1 - sz.start, Z)  # the p this d maps into the tile
                    if p0 < p1:
                        grad_padded[:, :, p0 + sz.start:p1 + sz.start, sy, sx].addcmul_(
                            grad_cost[:, i:i + 1, p0:p1], f0[:, :, p0:p1])
        grad_f1 = grad_padded[:, :, rz:rz + Z, ry:ry + Y, rx:rx + X] if need_f1 else None  # B×C×Z×Y×X
        return grad_f0, grad_f1, None


def mean_correlation_3d(reference: torch.Tensor, queries: torch.Tensor, radius: tuple[int, int, int]) -> torch.Tensor:
    """Spatial mean of the cost volume of one reference against R query volumes, as one 3D convolution.

    reference: B×C×Z×Y×X; queries: B×R×C×Z×Y×X; radius (rx, ry, rz) -> B×R×D with
    out[b, r, d] = mean_p cross_correlation_3d(reference[b], queries[b, r], radius)[d, p].

    Why a convolution: Σ_p ref(p − d)·q(p) is a 3D convolution (PyTorch's, i.e. a cross-correlation) of the
    zero-padded reference with the query as a kernel as large as the volume: output position o = r − d
    (per axis) reads ref_pad(p + o) = ref(p − d). The B examples are the groups of one call. It computes the
    same sums as the D shifted copies of the reference stacked into a D×(C·N) matrix for one GEMM (the
    earlier form), without writing those copies: on the small preset's half-resolution egomotion scale
    (C 16, 32×8×32, R 27, D 75, 1 thread) the stack alone was a 39 MB fresh tensor per call, and the whole
    function took 63 ms against 21 ms as a convolution. Autograd gives both gradients (the loop is the
    reference in tests/unit/egomotion/test_cost_volume.py).
    """
    check_shape("reference", reference, (None, None, None, None, None))
    B, C, Z, Y, X = reference.shape
    check_shape("queries", queries, (B, None, C, Z, Y, X))
    rx, ry, rz = (int(r) for r in radius)
    if min(rx, ry, rz) < 0:
        raise ShapeError(f"mean_correlation_3d: radius must be non-negative, got {radius}")
    R = queries.shape[1]
    padded = F.pad(reference, (rx, rx, ry, ry, rz, rz))  # B×C×(Z+2rz)×(Y+2ry)×(X+2rx)
    padded = padded.reshape(1, B * C, *padded.shape[-3:])  # 1×(B·C)×…: the examples as groups
    kernels = queries.reshape(B * R, C, Z, Y, X)  # (B·R)×C×Z×Y×X, example b's kernels form group b
    out = F.conv3d(padded, kernels, groups=B)  # 1×(B·R)×(2rz+1)×(2ry+1)×(2rx+1), index o = r − d per axis
    # Flip so that index d + r (z-major, from −r to r) matches `displacements`.
    return out.flip(-3, -2, -1).reshape(B, R, -1) / (Z * Y * X)  # B×R×D


@full_precision  # displacements in voxels: float32 under autocast
def soft_argmax_displacement(cost: torch.Tensor, radius: tuple[int, int, int], beta: torch.Tensor | float) -> torch.Tensor:
    """cost B×D×Z×Y×X (from `cross_correlation_3d` with the same radius) -> expected displacement B×3×Z×Y×X.

    flow(p) = Σ_d softmax_d(β · cost[:, d, p]) · d, channels (x, y, z) in voxels. A correlator that
    works before any training: where one displacement matches clearly it wins; where all match equally
    (empty space, the inside of a uniform surface) the weights spread symmetrically and the mean stays
    near zero.
    """
    disp = displacements(radius, device=cost.device, dtype=cost.dtype)  # D×3
    if cost.shape[1] != disp.shape[0]:
        raise ShapeError(f"soft_argmax_displacement: cost has {cost.shape[1]} displacements, radius {radius} "
                         f"gives {disp.shape[0]}")
    p = torch.softmax(beta * cost, dim=1)  # B×D×Z×Y×X
    B, D = p.shape[:2]
    # One GEMM over D on p as it lies (B×D×(Z·Y·X)). Why not einsum("bdzyx,dc->bczyx"): it first copies p
    # into B×Z×Y×X×D order, forward and backward (at the flow recipe's D 147 on the small grid ~80 MB each:
    # 410 ms per call against 110 ms, one thread; the same sums, bitwise equal there).
    flow = torch.matmul(disp.t(), p.reshape(B, D, -1))  # B×3×(Z·Y·X)
    return flow.reshape(B, 3, *p.shape[2:])  # B×3×Z×Y×X
