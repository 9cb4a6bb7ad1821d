"""Vectorised ray casting against a ground plane and oriented boxes.

Frames (docs/conventions.md#frames): `world` is gravity-aligned with Y down; `cam` is OpenCV (X right, Y down,
Z forward); `pix` integer coordinates are pixel centres. Boxes are canonical `(x, y, z, lx, ly, lz, yaw)`.

Rays are kept in affine form: the ray of pixel (u, v) is o + t·d with d = A @ (u, v, 1), where A is the
pixel -> direction map of the camera expressed in some frame, scaled so that d's cam-Z component is 1.
Hence the hit parameter t IS the depth (metres along camera Z), and per-pixel directions never need to be
stored: every kernel below builds them from (u, v) on the fly.

Pixels are handled in TILE-MAJOR order: index n = ((ty·TX + tx)·tile + dy)·tile + dx over the image
padded to Hp×Wp (multiples of `tile`); `tiles_to_image` turns such arrays back into C×H×W×….
Boxes are only tested on the tiles that their projected corners overlap, so the cost follows the image
area the boxes cover, not rays × boxes; the nearest hit per tile is a dense min over the boxes of that tile.
"""

from __future__ import annotations

import torch

from core.geometry import boxes as gboxes
from core.geometry import camera, se3


def ray_box_t(o_local: torch.Tensor, d_local: torch.Tensor, half: torch.Tensor, near: float) -> torch.Tensor:
    """Slab test of rays against boxes centred at the origin of their own frame (the obvious form; the
    tiled caster below is the same test, unrolled over axes).

    o_local, d_local, half: ...×3 (ray origin, direction, box half-lengths, all in the box frame)
    -> t: ... entry parameter of the ray (inf where it misses or enters at t <= near).
    A zero direction component gives ±inf slab bounds (IEEE division), which the min/max handle.
    """
    t1 = (-half - o_local) / d_local
    t2 = (half - o_local) / d_local
    t_enter = torch.minimum(t1, t2).amax(-1)
    t_exit = torch.maximum(t1, t2).amin(-1)
    hit = (t_exit >= t_enter) & (t_enter > near)
    return torch.where(hit, t_enter, torch.full_like(t_enter, float("inf")))


def ray_affine(pix_T_cam: torch.Tensor, frame_T_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Affine ray form of C cameras in a frame: (origin: C×3, A: C×3×3) with d(u, v) = A @ (u, v, 1).

    pix_T_cam, frame_T_cam: C×4×4. A's columns are d(1,0)−d(0,0), d(0,1)−d(0,0) and d(0,0), read off
    `camera.unproject` at depth 1 (so the pinhole model lives in one place).
    """
    C = pix_T_cam.shape[0]
    uv = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=pix_T_cam.dtype,
                      device=pix_T_cam.device).expand(C, 3, 2)
    d = camera.unproject(pix_T_cam, uv, torch.ones(C, 3, dtype=pix_T_cam.dtype, device=pix_T_cam.device))  # C×3×3
    A_cam = torch.stack([d[:, 1] - d[:, 0], d[:, 2] - d[:, 0], d[:, 0]], dim=-1)  # C×3×3, columns
    return frame_T_cam[:, :3, 3], frame_T_cam[:, :3, :3] @ A_cam


def tile_pixels(H: int, W: int, tile: int, *, dtype: torch.dtype = torch.float32,
                device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates (u, v), each Hp·Wp, in tile-major order (padding pixels included)."""
    Hp, Wp = -(-H // tile) * tile, -(-W // tile) * tile
    TY, TX = Hp // tile, Wp // tile
    ty = torch.arange(TY, device=device).view(TY, 1, 1, 1)
    tx = torch.arange(TX, device=device).view(1, TX, 1, 1)
    dy = torch.arange(tile, device=device).view(1, 1, tile, 1)
    dx = torch.arange(tile, device=device).view(1, 1, 1, tile)
    u = (tx * tile + dx).expand(TY, TX, tile, tile).reshape(-1)  # Hp·Wp
    v = (ty * tile + dy).expand(TY, TX, tile, tile).reshape(-1)  # Hp·Wp
    return u.to(dtype), v.to(dtype)


def tiles_to_image(x: torch.Tensor, H: int, W: int, tile: int) -> torch.Tensor:
    """C×(Hp·Wp)×… in tile-major order -> C×H×W×… (padding cropped)."""
    C, rest = x.shape[0], x.shape[2:]
    Hp, Wp = -(-H // tile) * tile, -(-W // tile) * tile
    x = x.reshape(C, Hp // tile, Wp // tile, tile, tile, *rest)  # C×TY×TX×tile×tile×…
    x = x.transpose(2, 3).reshape(C, Hp, Wp, *rest)  # C×TY×tile×TX×tile×… -> C×Hp×Wp×…
    return x[:, :H, :W]


def _tile_cover(boxes_world: torch.Tensor, valid: torch.Tensor, pix_T_cam: torch.Tensor,
                cam_T_world: torch.Tensor, H: int, W: int, tile: int, near: float) -> torch.Tensor:
    """C×TY×TX×B bool: tiles that a box's projection may touch. Boxes reaching behind the camera cover
    the whole image (conservative); boxes wholly behind it or off the image cover nothing."""
    C, B = boxes_world.shape[:2]
    TY, TX = -(-H // tile), -(-W // tile)
    corners = gboxes.box_corners(boxes_world)  # C×B×8×3
    uv, z = camera.project(pix_T_cam, se3.apply(cam_T_world, corners.reshape(C, B * 8, 3)))
    uv, z = uv.reshape(C, B, 8, 2), z.reshape(C, B, 8)  # C×B×8×2, C×B×8
    straddles = (z <= near).any(-1)  # C×B
    behind = (z <= near).all(-1)
    # Pixel i covers u in [i-0.5, i+0.5]; grow by one pixel against rounding.
    u0 = torch.where(straddles, 0.0, torch.floor(uv[..., 0].amin(-1) + 0.5) - 1)
    u1 = torch.where(straddles, W - 1.0, torch.floor(uv[..., 0].amax(-1) + 0.5) + 1)
    v0 = torch.where(straddles, 0.0, torch.floor(uv[..., 1].amin(-1) + 0.5) - 1)
    v1 = torch.where(straddles, H - 1.0, torch.floor(uv[..., 1].amax(-1) + 0.5) + 1)
    seen = valid & ~behind & (u1 >= 0) & (u0 <= W - 1) & (v1 >= 0) & (v0 <= H - 1)  # C×B
    tx0, tx1 = (u0.clamp(0, W - 1).long() // tile), (u1.clamp(0, W - 1).long() // tile)
    ty0, ty1 = (v0.clamp(0, H - 1).long() // tile), (v1.clamp(0, H - 1).long() // tile)
    ty = torch.arange(TY, device=boxes_world.device).view(1, TY, 1, 1)
    tx = torch.arange(TX, device=boxes_world.device).view(1, 1, TX, 1)
    return (seen[:, None, None] & (ty >= ty0[:, None, None]) & (ty <= ty1[:, None, None])
            & (tx >= tx0[:, None, None]) & (tx <= tx1[:, None, None]))  # C×TY×TX×B


def cast_boxes(pix_T_cam: torch.Tensor, world_T_cam: torch.Tensor, boxes_world: torch.Tensor,
               valid: torch.Tensor, H: int, W: int, *, tile: int = 16,
               near: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest box hit of every pixel ray.

    pix_T_cam, world_T_cam: C×4×4; boxes_world: C×B×7 (the boxes camera c sees, e.g. those of its time
    step); valid: C×B bool -> (t: C×(Hp·Wp) depth of the hit, inf = no box; box: C×(Hp·Wp) int64 box
    column, -1 = no box), both in tile-major pixel order.
    """
    C, B = boxes_world.shape[:2]
    device, dtype = pix_T_cam.device, pix_T_cam.dtype
    TY, TX = -(-H // tile), -(-W // tile)
    n_tiles, tt = C * TY * TX, tile * tile
    t_out = torch.full((n_tiles, tt), float("inf"), dtype=dtype, device=device)
    box_out = torch.full((n_tiles, tt), -1, dtype=torch.long, device=device)
    if B == 0:
        return t_out.reshape(C, -1), box_out.reshape(C, -1)
    cover = _tile_cover(boxes_world, valid, pix_T_cam, se3.invert(world_T_cam), H, W, tile, near)  # C×TY×TX×B
    pc, pty, ptx, pb = cover.nonzero(as_tuple=True)  # P each, grouped by tile
    if pc.numel() == 0:
        return t_out.reshape(C, -1), box_out.reshape(C, -1)

    # Per pair: the ray map and origin in the box's own frame.
    origin, A = ray_affine(pix_T_cam, world_T_cam)  # C×3, C×3×3
    obj_T_world = se3.invert(gboxes.box_T_obj(boxes_world))  # C×B×4×4
    R = obj_T_world[pc, pb, :3, :3]  # P×3×3
    o = (R @ origin[pc].unsqueeze(-1)).squeeze(-1) + obj_T_world[pc, pb, :3, 3]  # P×3
    A_loc = R @ A[pc]  # P×3×3
    half = 0.5 * boxes_world[pc, pb, 3:6]  # P×3
    lo, hi = -half - o, half - o  # P×3: slab bounds relative to the origin
    u0 = (ptx * tile).to(dtype)
    v0 = (pty * tile).to(dtype)
    steps = torch.arange(tile, dtype=dtype, device=device)  # tile

    t_enter = t_exit = None
    for k in range(3):  # unrolled slab test, all pairs × tile² pixels at once
        base = A_loc[:, k, 0] * u0 + A_loc[:, k, 1] * v0 + A_loc[:, k, 2]  # P
        row = base[:, None] + A_loc[:, k, 0:1] * steps  # P×tile (along dx)
        col = A_loc[:, k, 1:2] * steps  # P×tile (along dy)
        d = col[:, :, None] + row[:, None, :]  # P×tile×tile
        ta = lo[:, k, None, None] / d
        tb = hi[:, k, None, None] / d
        near_k, far_k = torch.minimum(ta, tb), torch.maximum(ta, tb)
        t_enter = near_k if t_enter is None else torch.maximum(t_enter, near_k)
        t_exit = far_k if t_exit is None else torch.minimum(t_exit, far_k)
    hit = (t_exit >= t_enter) & (t_enter > near)
    t = torch.where(hit, t_enter, float("inf")).reshape(-1, tt)  # P×tile²

    # Nearest hit per tile: scatter pairs into a dense (tile slot × rank × pixel) block, min over rank.
    count = cover.sum(-1).reshape(-1)  # n_tiles
    rank = (cover.cumsum(-1) - 1)[pc, pty, ptx, pb]  # P, position of the pair among its tile's boxes
    tile_of = (pc * TY + pty) * TX + ptx  # P
    used = (count > 0).nonzero(as_tuple=True)[0]  # S tiles with any box
    slot_of_tile = torch.full((n_tiles,), -1, dtype=torch.long, device=device)
    slot_of_tile[used] = torch.arange(used.numel(), device=device)
    slot = slot_of_tile[tile_of]  # P
    M = int(count.max())
    dense = torch.full((used.numel(), M, tt), float("inf"), dtype=dtype, device=device)
    dense[slot, rank] = t
    which = torch.full((used.numel(), M), -1, dtype=torch.long, device=device)
    which[slot, rank] = pb
    t_min, arg = dense.min(dim=1)  # S×tile²
    box_min = torch.where(torch.isfinite(t_min), which.gather(1, arg), -1)
    t_out[used] = t_min
    box_out[used] = box_min
    return t_out.reshape(C, -1), box_out.reshape(C, -1)


def cast_ground(origin: torch.Tensor, A: torch.Tensor, u: torch.Tensor, v: torch.Tensor, ground_y: float,
                near: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Hit of every pixel ray with the plane y = ground_y of a gravity-aligned frame (Y down).

    origin: C×3, A: C×3×3 (`ray_affine` in that frame), u, v: N pixel coordinates
    -> (t: C×N, inf where the ray points up or the hit is before `near`; d_y: C×N the rays' Y component).
    """
    d_y = A[:, 1, 0:1] * u + A[:, 1, 1:2] * v + A[:, 1, 2:3]  # C×N
    t = (ground_y - origin[:, 1:2]) / d_y
    return torch.where((d_y > 0) & (t > near), t, float("inf")), d_y
