"""Procedural textures: value noise (a periodic random lattice sampled bilinearly), checker and stripes.

Textures are functions of a point's position in the surface's own frame (the object frame for boxes,
`ref0` x/z for the ground), so a surface looks the same from every view and at every time step —
which is what lets view-contrastive learning match it. All functions are batched torch on the points'
device. The lattice is drawn per record from the record's seeded generator (on the CPU), so a seed
gives the same pattern on CPU and CUDA.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

# Texture kinds (column KIND of a texture table).
CHECKER, STRIPES, NOISE = 0, 1, 2

# Layout of one row of a texture table (float, N_TEX columns).
KIND, SCALE, SEED, AXIS = 0, 1, 2, 3
COLOUR_A = slice(4, 7)
COLOUR_B = slice(7, 10)
N_TEX = 10

LATTICE = 256        # period of the noise lattice, in lattice cells
NOISE_CHANNELS = 2   # independent noise fields in one lattice


def noise_lattice(generator: torch.Generator, device: torch.device | str) -> torch.Tensor:
    """1×NOISE_CHANNELS×(L+1)×(L+1) uniform noise with the first row/column repeated at the end, so
    bilinear sampling of coordinates taken modulo L is seamless (L = LATTICE)."""
    base = torch.rand(NOISE_CHANNELS, LATTICE, LATTICE, generator=generator)  # C×L×L
    base = torch.cat([base, base[:, :1]], dim=1)  # C×(L+1)×L
    base = torch.cat([base, base[:, :, :1]], dim=2)  # C×(L+1)×(L+1)
    return base.unsqueeze(0).to(device)


def sample_noise(lattice: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Value noise at lattice coordinates: coords R×N×2 (R sets of (a, b) points; overwritten in place)
    -> R×NOISE_CHANNELS×N in [0, 1]."""
    # Periodic wrap, then align_corners=True normalisation: -1 is texel 0, +1 is texel L.
    grid = coords.remainder_(LATTICE).mul_(2.0 / LATTICE).sub_(1.0)
    out = F.grid_sample(lattice, grid.unsqueeze(0), mode="bilinear", align_corners=True)  # 1×C×R×N
    return out[0].transpose(0, 1)  # R×C×N


def _coords(*pairs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """R pairs of N-vectors (a, b) -> R×N×2 coordinates for `sample_noise`."""
    a0 = pairs[0][0]
    out = torch.empty(len(pairs), a0.shape[0], 2, dtype=a0.dtype, device=a0.device)
    for r, (a, b) in enumerate(pairs):
        out[r, :, 0] = a
        out[r, :, 1] = b
    return out


def face_coordinates(p: torch.Tensor, face_axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """2D coordinates on a box face: the two local axes other than the face normal's.

    p: N×3 (object frame), face_axis: N int64 in {0, 1, 2} -> (a, b): two N tensors (metres).
    """
    x, y, z = p.unbind(-1)
    return torch.where(face_axis == 0, z, x), torch.where(face_axis == 1, z, y)


def object_albedo(p_local: torch.Tensor, face_axis: torch.Tensor, half: torch.Tensor, table: torch.Tensor,
                  lattice: torch.Tensor) -> torch.Tensor:
    """Albedo of box surface points.

    p_local: N×3 hit points in the object frame, face_axis: N (local axis the face is normal to),
    half: N×3 half-lengths, table: N×N_TEX texture rows of the hit objects, lattice: `noise_lattice`
    -> N×3 in [0, 1]. Coordinates start at the box's min corner, so patterns do not mirror about the
    centre; every face gets its own patch of noise.
    """
    a, b = face_coordinates(p_local + half, face_axis)  # metres from the min corner
    scale = table[:, SCALE]
    u, v = a / scale, b / scale
    seed = table[:, SEED] + face_axis.to(a.dtype) * 97.0  # offset into the lattice, per object and face
    checker = (torch.floor(u) + torch.floor(v)).remainder(2.0)
    along = torch.where(table[:, AXIS] > 0.5, v, u + 0.5 * v)  # horizontal or diagonal stripes
    stripes = torch.floor(along * 2.0).remainder(2.0)
    n = sample_noise(lattice, _coords((u * 1.5 + seed, v * 1.5 + 0.37 * seed),  # pattern noise
                                      (a * 4.0 + seed, b * 4.0 + 0.37 * seed)))  # fine detail; 2×C×N
    noise, detail = n[0, 0], n[1, 1] - 0.5
    kind = table[:, KIND]
    mix = torch.where(kind == CHECKER, checker, torch.where(kind == STRIPES, stripes, noise))  # N
    colour = torch.lerp(table[:, COLOUR_A], table[:, COLOUR_B], mix.unsqueeze(-1))  # N×3
    return (colour * (1.0 + 0.3 * detail.unsqueeze(-1))).clamp(0.0, 1.0)


# Ground albedo per class: road, pavement, earth; and the lane paint.
_GROUND_PALETTE = ((0.27, 0.27, 0.29), (0.55, 0.53, 0.50), (0.40, 0.45, 0.22))
_PAINT = (0.9, 0.85, 0.55)


def ground_albedo(x: torch.Tensor, z: torch.Tensor, lattice: torch.Tensor, *, road_half_width: float,
                  sidewalk_width: float, noise_scale: float) -> torch.Tensor:
    """Albedo of ground points at (x, z) in `ref0` metres (the road runs along z): N, N -> N×3.

    Asphalt with lane markings on the road, paving slabs on the sidewalks, earth beyond; value noise at
    two scales modulates everything, so every patch of ground is locally distinctive.
    """
    inv = 1.0 / noise_scale
    n = sample_noise(lattice, _coords((x * inv, z * inv), (x * (0.25 * inv) + 101.0, z * (0.25 * inv) + 57.0)))  # 2×C×N
    grain = 0.55 * n[0, 0] + 0.45 * n[1, 1]  # N in [0, 1]
    ax = x.abs()
    cls = (ax >= road_half_width).long() + (ax >= road_half_width + sidewalk_width).long()  # N: 0 road, 1 walk, 2 earth
    palette = torch.tensor(_GROUND_PALETTE, dtype=x.dtype, device=x.device)
    slab = (torch.floor(x * 1.25) + torch.floor(z * 1.25)).remainder(2.0) * (cls == 1)  # 0.8 m paving slabs
    albedo = palette[cls] * (0.55 + 0.9 * grain + 0.2 * slab).unsqueeze(-1)  # N×3
    paint = (cls == 0) & (((ax < 0.12) & (z.remainder(6.0) < 3.0))
                          | ((ax > road_half_width - 0.35) & (ax < road_half_width - 0.2)))
    return torch.where(paint.unsqueeze(-1), torch.tensor(_PAINT, dtype=x.dtype, device=x.device), albedo).clamp(0, 1)


def sky_colour(up: torch.Tensor) -> torch.Tensor:
    """Sky for rays that hit nothing: up = ... upward component of the unit ray direction -> ...×3."""
    k = up.clamp(0.0, 1.0).unsqueeze(-1)
    horizon = torch.tensor([0.78, 0.82, 0.86], device=up.device, dtype=up.dtype)
    zenith = torch.tensor([0.35, 0.55, 0.85], device=up.device, dtype=up.dtype)
    return torch.lerp(horizon, zenith, k)
