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
NOISE_CHANNELS = 3   # independent noise fields in one lattice


def noise_lattice(generator: torch.Generator, device: torch.device | str) -> torch.Tensor:
    """1×NOISE_CHANNELS×(L+1)×(L+1) uniform noise with the first row/column repeated at the end, so
    bilinear sampling of coordinates taken modulo L is seamless (L = LATTICE)."""
    base = torch.rand(NOISE_CHANNELS, LATTICE, LATTICE, generator=generator)  # C×L×L
    base = torch.cat([base, base[:, :1]], dim=1)  # C×(L+1)×L
    base = torch.cat([base, base[:, :, :1]], dim=2)  # C×(L+1)×(L+1)
    return base.unsqueeze(0).to(device)


def sample_noise(lattice: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Value noise at lattice coordinates: a, b: R×N (R coordinate sets) -> R×NOISE_CHANNELS×N in [0, 1]."""
    R, N = a.shape
    scale = 2.0 / LATTICE  # align_corners=True: -1 is texel 0, +1 is texel L
    grid = torch.stack([a.remainder(LATTICE) * scale - 1.0, b.remainder(LATTICE) * scale - 1.0], dim=-1)  # R×N×2
    out = F.grid_sample(lattice, grid.unsqueeze(0), mode="bilinear", align_corners=True)  # 1×C×R×N
    return out[0].transpose(0, 1)  # R×C×N


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
    ca = torch.stack([u * 1.5 + seed, a * 4.0 + seed])  # 2×N: pattern noise, fine detail
    cb = torch.stack([v * 1.5 + 0.37 * seed, b * 4.0 + 0.37 * seed])
    n = sample_noise(lattice, ca, cb)  # 2×C×N
    noise, detail = n[0, 0], n[1, 1] - 0.5
    kind = table[:, KIND]
    mix = torch.where(kind == CHECKER, checker, torch.where(kind == STRIPES, stripes, noise))  # N
    colour = torch.lerp(table[:, COLOUR_A], table[:, COLOUR_B], mix.unsqueeze(-1))  # N×3
    return (colour * (1.0 + 0.3 * detail.unsqueeze(-1))).clamp(0.0, 1.0)


def ground_albedo(x: torch.Tensor, z: torch.Tensor, lattice: torch.Tensor, *, road_half_width: float,
                  sidewalk_width: float, noise_scale: float) -> torch.Tensor:
    """Albedo of ground points at (x, z) in `ref0` metres (the road runs along z): N, N -> N×3.

    Asphalt with lane markings on the road, paving slabs on the sidewalks, patchy earth beyond; value
    noise at two scales on top so every patch of ground is locally distinctive.
    """
    n = sample_noise(lattice, torch.stack([x / noise_scale, x / (4 * noise_scale) + 101.0]),
                     torch.stack([z / noise_scale, z / (4 * noise_scale) + 57.0]))  # 2×C×N
    n1, n2, n3 = n[0, 0], n[1, 1], n[0, 2]
    grain = 0.55 * n1 + 0.45 * n2  # N in [0, 1]
    ax = x.abs()
    asphalt = 0.16 + 0.24 * grain
    road = torch.stack([asphalt, asphalt, asphalt * 1.06], -1)  # N×3
    paint = (((ax < 0.12) & (z.remainder(6.0) < 3.0))
             | ((ax > road_half_width - 0.35) & (ax < road_half_width - 0.2))).unsqueeze(-1)
    road = torch.where(paint, torch.tensor([0.9, 0.85, 0.55], device=x.device, dtype=x.dtype), road)
    slab = (torch.floor(x * 1.25) + torch.floor(z * 1.25)).remainder(2.0)  # 0.8 m paving slabs
    pave = 0.5 + 0.12 * slab + 0.2 * (grain - 0.5)
    pavement = torch.stack([pave, pave * 0.97, pave * 0.92], -1)
    earth = torch.stack([0.22 + 0.25 * n2 + 0.1 * n3, 0.3 + 0.3 * n1, 0.12 + 0.12 * grain], -1)
    return torch.where((ax < road_half_width).unsqueeze(-1), road,
                       torch.where((ax < road_half_width + sidewalk_width).unsqueeze(-1), pavement, earth)).clamp(0, 1)


def sky_colour(up: torch.Tensor) -> torch.Tensor:
    """Sky for rays that hit nothing: up = ... upward component of the unit ray direction -> ...×3."""
    k = up.clamp(0.0, 1.0).unsqueeze(-1)
    horizon = torch.tensor([0.78, 0.82, 0.86], device=up.device, dtype=up.dtype)
    zenith = torch.tensor([0.35, 0.55, 0.85], device=up.device, dtype=up.dtype)
    return torch.lerp(horizon, zenith, k)
