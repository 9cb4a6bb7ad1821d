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
    rx, ry, rz = (int(r) for r in radius)
    if min(rx, ry, rz) < 0:
        raise ShapeError(f"cross_correlation_3d: radius must be non-negative, got {radius}")
    _, C, Z, Y, X = f0.shape
    padded = F.pad(f1, (rx, rx, ry, ry, rz, rz))  # B×C×(Z+2rz)×(Y+2ry)×(X+2rx)
    costs = []
    for dz in range(2 * rz + 1):
        for dy in range(2 * ry + 1):
            for dx in range(2 * rx + 1):
                shifted = padded[:, :, dz:dz + Z, dy:dy + Y, dx:dx + X]  # B×C×Z×Y×X
                costs.append((f0 * shifted).sum(dim=1))  # B×Z×Y×X
    cost = torch.stack(costs, dim=1)  # B×D×Z×Y×X
    return cost / C if normalize else cost


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
    return torch.einsum("bdzyx,dc->bczyx", p, disp)  # B×3×Z×Y×X
