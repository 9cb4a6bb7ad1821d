"""Do a pair of stabilised 3D volumes carry the objects' motion? The matchability test under 3D flow.

    python tests/benchmarks/bench_flow_features.py --data DIR [--bundle B ...] [--records 16]
        [--radius 3 1 3] [--threads 1]

For each record of DIR (t = 0 → 1, both maps lifted into ref_0 with the record poses, as the flow
bench does) and each compared pair — the fused 4-channel input volumes, and the mapper's maps of each
`--bundle` (its `mapper` module) — this scores every occupied voxel of t against the voxels of t+1
within ±radius (x, y, z) by cosine similarity, and prints, over the occupied voxels of moving objects
(true flow ≥ 0.5 voxel) and over static occupied voxels:
- hit: the best-scoring integer shift equals the rounded true flow (moving) / is zero (static);
- moved: (moving only) the best shift is not zero;
- margin: cos(true shift) − cos(zero shift), mean (moving: positive = the motion is visible);
- sharp: cos(best) − the mean cos over all shifts (how peaked the similarity is).
A flow module trained on a pair whose moving-voxel `hit` is near zero cannot beat zero motion: the
motion is not in what it compares. One JSON line per (pair, split) follows the table.

Then, per bundle, two controlled tests that separate the encoder from the data. Object shift: in view 0's
input volume of t, only the voxels inside the moving objects' boxes are moved by d = 1, 2, 3 voxels along x
(the vacated voxels emptied), the encoder is run on both, and the cosine of f0(p) with the moved encoding
at p + d (true shift) and at p (zero shift) is averaged over the objects' occupied voxels. A negative
margin here means the encoder itself does not let features follow an object (context or aliasing
dominate); a positive one with a negative margin on real pairs points at the data instead (rays smeared
with the object's colour, occlusion, multi-view fusion). Scene shift: the whole input volume moves d = 1,
2, 3, 8 voxels (content and context together), so "content" (cosine at p + d) above "position" (at p)
means the features go with what they encode; features that follow only d = 8 change only on the
encoder's stride-8 lattice (aliased).

Measured (small preset, 64 training records, contrastive pretraining 400 steps × batch 2, 16 test records,
radius 3 1 3; one seed): real pairs, moving voxels' margin: input volume +0.099, the paper's encoder
layers −0.070, with a 16-channel full-resolution branch (Encoder3D.full_res) −0.047 (the same with the 3D
contrastive terms sampled on occupied voxels only: −0.273). Controlled object shift d = 1/2/3: paper
layers −0.038/−0.028/−0.045, full-resolution branch +0.083/+0.099/+0.155.
Session 7 (same data, 400 steps, seed 0, with the pretraining's local matching term, `--match-weight`):
moving voxels' hit / margin, volume 0.147 / +0.099; paper layers 0.050 / −0.076 without the term, 0.167 /
−0.003 at weight 0.25, 0.153 / −0.011 at 1.0; full-resolution branch (16) 0.213 / +0.016 at 0.25, 0.249 /
+0.051 at 1.0 (controlled shift +0.31/+0.32/+0.40). Static hit falls from 0.89 to 0.74-0.86.
Session 19 (scene shift, 600-step pretrainings of seed 0 on the 64 training records, 8 held-out records of
data seed 7): the paper's objectives alone (no matching or occupancy term) — contrastive content / position
0.78 / 0.86, 0.51 / 0.81, 0.27 / 0.74 at d = 1, 2, 3 and 0.97 / 0.52 at d = 8 (aliased), regression 0.96 /
0.94, 0.94 / 0.82, 0.92 / 0.71; contrastive with `shift_positives` 3: 0.89 / 0.84, 0.83 / 0.77, 0.81 / 0.69
(docs/findings.md, "View-contrastive features are aliased").
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time

import torch

from core.bundle import load_bundle
from core.data.batch import records_to_batch
from core.data.ground_truth import gt_flow, gt_moving_mask, gt_occupancy
from core.data.shards import ShardDataset
from core.geometry.shift import shift_voxels
from core.models.cost_volume import cross_correlation_3d, displacements
from core.models.egomotion_inputs import fused_input_volume
from core.models.input_volume import input_volume
from core.models.normalize import l2_normalize_channels
from core.presets import get_preset
from core.tasks.poses import cam_T_ref


def shift_scores(f0: torch.Tensor, f1: torch.Tensor, radius: tuple[int, int, int]) -> torch.Tensor:
    """f0, f1: 1×C×Z×Y×X -> cosine of f0(p) with f1(p + d) for every shift d: D×Z×Y×X (D z-major)."""
    return cross_correlation_3d(l2_normalize_channels(f0), l2_normalize_channels(f1), radius)[0]


def pair_stats(scores: torch.Tensor, disp: torch.Tensor, flow: torch.Tensor, moving: torch.Tensor,
               static: torch.Tensor) -> dict[str, dict[str, float]]:
    """scores D×Z×Y×X, disp D×3 (x, y, z), flow 3×Z×Y×X, masks Z×Y×X bool -> sums per split."""
    zero = int(((disp == 0).all(1)).nonzero()[0])
    best = scores.argmax(0)  # Z×Y×X
    best_d = disp[best].permute(3, 0, 1, 2)  # 3×Z×Y×X
    r = disp.abs().amax(0)  # (rx, ry, rz)
    want = torch.maximum(torch.minimum(flow.round(), r.view(3, 1, 1, 1)), -r.view(3, 1, 1, 1))  # 3×Z×Y×X
    # index of the rounded true shift in the z-major order of `displacements`
    nx, ny = 2 * int(r[0]) + 1, 2 * int(r[1]) + 1
    idx = ((want[2] + r[2]) * ny * nx + (want[1] + r[1]) * nx + (want[0] + r[0])).long()  # Z×Y×X
    cos_true = scores.gather(0, idx[None])[0]
    cos_zero = scores[zero]
    sharp = scores.max(0).values - scores.mean(0)
    out = {}
    for name, mask in (("moving", moving), ("static", static)):
        n = int(mask.sum())
        if name == "moving":
            hit = (best_d == want).all(0)
        else:
            hit = best == zero
        out[name] = {"n": n, "hit": float(hit[mask].sum()), "moved": float((best != zero)[mask].sum()),
                     "margin": float((cos_true - cos_zero)[mask].sum()), "sharp": float(sharp[mask].sum())}
    return out


@torch.no_grad()
def controlled_object_shift(mapper, records, grid, shifts=(1, 2, 3)) -> dict[int, dict[str, float]]:
    """Move only the moving objects' input voxels (view 0 of t) by d along x; mean cosines over their occupied
    voxels of f0(p) with the re-encoded volume at p + d ("true") and at p ("zero"). -> {d: {...}}."""
    sums: dict[int, list[float]] = {d: [0.0, 0.0, 0] for d in shifts}
    for rec in records:
        b = records_to_batch([rec])
        mask = gt_moving_mask(rec, 0, grid)[None] > 0  # 1×1×Z×Y×X
        v, _ = input_volume(b["rgb"][0, 0], b["depth"][0, 0], b["pix_T_cam"][0], cam_T_ref(b, 0, 0)[0], grid)  # 1×4×Z×Y×X
        occ = (v[:, :1] > 0) & mask
        if int(occ.sum()) == 0:
            continue
        f0 = mapper.encoder(v)  # 1×F×Z×Y×X
        obj = torch.where(mask, v, torch.zeros_like(v))
        vacated = torch.where(mask, torch.zeros_like(v), v)
        for d in shifts:
            moved_obj, moved_mask = torch.zeros_like(obj), torch.zeros_like(mask)
            moved_obj[..., d:], moved_mask[..., d:] = obj[..., :-d], mask[..., :-d]
            f1 = mapper.encoder(torch.where(moved_mask, moved_obj, vacated))  # 1×F×Z×Y×X
            at_true = torch.zeros_like(f1)
            at_true[..., :-d] = f1[..., d:]  # f1(p + d) stored at p
            sums[d][0] += float((f0 * at_true).sum(1, keepdim=True)[occ].sum())
            sums[d][1] += float((f0 * f1).sum(1, keepdim=True)[occ].sum())
            sums[d][2] += int(occ.sum())
    return {d: {"cos_true": t / max(n, 1), "cos_zero": z / max(n, 1), "margin": (t - z) / max(n, 1), "voxels": n}
            for d, (t, z, n) in sums.items()}


@torch.no_grad()
def controlled_scene_shift(mapper, records, grid, shifts=(1, 2, 3, 8)) -> dict[int, dict[str, float]]:
    """Move view 0's WHOLE input volume of t by d voxels along x (content and context together: the scene
    lifted into a grid moved by d), re-encode, and average over the occupied voxels whose p + d stays inside
    the cosine of f0(p) with f1(p + d) ("content": the feature went with what it encodes) and with f1(p)
    ("position": it stayed with the grid). -> {d: {...}}."""
    sums: dict[int, list[float]] = {d: [0.0, 0.0, 0] for d in shifts}
    for rec in records:
        b = records_to_batch([rec])
        v, _ = input_volume(b["rgb"][0, 0], b["depth"][0, 0], b["pix_T_cam"][0], cam_T_ref(b, 0, 0)[0], grid)  # 1×4×Z×Y×X
        f0 = l2_normalize_channels(mapper.encoder(v))  # 1×F×Z×Y×X
        for d in shifts:
            f1 = l2_normalize_channels(mapper.encoder(shift_voxels(v, (d, 0, 0))))  # 1×F×Z×Y×X
            occ = v[:, :1] > 0
            occ[..., -d:] = False  # p + d inside
            at_content = shift_voxels(f1, (-d, 0, 0))  # f1(p + d) stored at p
            sums[d][0] += float((f0 * at_content).sum(1, keepdim=True)[occ].sum())
            sums[d][1] += float((f0 * f1).sum(1, keepdim=True)[occ].sum())
            sums[d][2] += int(occ.sum())
    return {d: {"cos_content": c / max(n, 1), "cos_position": q / max(n, 1), "voxels": n}
            for d, (c, q, n) in sums.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--bundle", action="append", default=[], help="NAME=DIR of a bundle with a mapper (repeatable)")
    ap.add_argument("--records", type=int, default=16)
    ap.add_argument("--radius", type=int, nargs=3, default=(3, 1, 3), metavar=("RX", "RY", "RZ"))
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print("command: python " + " ".join(shlex.quote(a) for a in sys.argv), f"| load {os.getloadavg()[0]:.2f}", flush=True)
    ds = ShardDataset(args.data)
    preset = None
    mappers = {}
    for item in args.bundle:
        name, _, path = item.partition("=")
        b = load_bundle(path, only=["mapper"])
        mappers[name] = b.modules["mapper"]
        preset = b.preset
    if preset is None:
        preset = get_preset(ds.manifest["preset"])
    grid = preset.grid
    radius = tuple(args.radius)
    disp = displacements(radius).long()
    totals: dict[str, dict[str, dict[str, float]]] = {}
    t0 = time.time()
    records = [ds[i] for i in range(min(args.records, len(ds)))]  # decoded once, used by both tests
    for rec in records:
        b = records_to_batch([rec])
        flow = gt_flow(rec, 0, grid)  # 3×Z×Y×X
        occ = gt_occupancy(rec, 0, grid)[0] > 0.5  # Z×Y×X
        mag = flow.norm(dim=0)
        moving, static = occ & (mag >= 0.5), occ & (mag < 1e-6)
        cam0, cam1 = cam_T_ref(b, 0, 0), cam_T_ref(b, 1, 0)
        pairs = {"volume": (fused_input_volume(b["rgb"][:, 0], b["depth"][:, 0], b["pix_T_cam"], cam0, grid),
                            fused_input_volume(b["rgb"][:, 1], b["depth"][:, 1], b["pix_T_cam"], cam1, grid))}
        with torch.no_grad():
            for name, m in mappers.items():
                pairs[name] = (m(b["rgb"][:, 0], b["depth"][:, 0], b["pix_T_cam"], cam0),
                               m(b["rgb"][:, 1], b["depth"][:, 1], b["pix_T_cam"], cam1))
        for name, (f0, f1) in pairs.items():
            s = pair_stats(shift_scores(f0, f1, radius), disp, flow, moving, static)
            acc = totals.setdefault(name, {})
            for split, d in s.items():
                a = acc.setdefault(split, {k: 0.0 for k in d})
                for k, v in d.items():
                    a[k] += v
    print(f"{len(records)} records of {args.data}, radius {radius}, {time.time() - t0:.0f} s")
    print(f"| {'pair':<14} | split  | voxels | hit   | moved | margin  | sharp |")
    rows = []
    for name, acc in totals.items():
        for split, a in acc.items():
            n = max(a["n"], 1.0)
            row = {"pair": name, "split": split, "voxels": int(a["n"]), "hit": a["hit"] / n,
                   "moved": a["moved"] / n, "margin": a["margin"] / n, "sharp": a["sharp"] / n}
            rows.append(row)
            print(f"| {name:<14} | {split:<6} | {row['voxels']:6d} | {row['hit']:.3f} | {row['moved']:.3f} | "
                  f"{row['margin']:+.4f} | {row['sharp']:.3f} |")
    for row in rows:
        print(json.dumps(row))
    tests = (("controlled object shift (view 0's input: only the moving objects' voxels move d along x):",
              controlled_object_shift, "controlled_shift",
              "cos true {cos_true:.3f} | cos zero {cos_zero:.3f} | margin {margin:+.3f}"),
             ("controlled scene shift (view 0's whole input moves d along x: content vs grid position):",
              controlled_scene_shift, "scene_shift", "cos content {cos_content:.3f} | cos position {cos_position:.3f}"))
    for title, test, key, cells in tests if mappers else ():
        print("\n" + title)
        for name, m in mappers.items():
            for d, r in test(m, records, grid).items():
                print(f"| {name:<14} | d={d} | " + cells.format(**r) + f" | {r['voxels']} voxels |")
                print(json.dumps({"pair": name, key: d, **r}))

if __name__ == "__main__":
    main()
