"""Why is the egomotion module less precise than ICP? Per-scale errors, quantisation floors, refinement.

    python tests/benchmarks/bench_egomotion_precision.py --data DIR [--bundle B ...] [--all-pairs]
        [--attach-refine] [--coarse-only] [--floors] [--threads 1]

On the moving-camera pairs of DIR (t = 0 → 1, as the paper bench's egomotion row; `--all-pairs`: every
pair) it prints mean rotation (rad) / translation (m) errors of:
- identity and point-to-plane ICP (exactly as core.eval.protocols.egomotion);
- per bundle: the module after each coarse scale (`per_scale`), after its sub-voxel stage if it has one,
  and its forward time per pair (median, `--threads` torch threads); per scale also the integer-lattice
  oracle: the best HARD choice the scale could make from the estimate entering it (the candidate
  rotation nearest the true residual, the true translation residual rounded to the scale's voxels and
  clipped to its radius) — the quantisation floor of an argmax (the soft-argmax and the residual MLP
  can interpolate below it). `--attach-refine` gives a bundle without a sub-voxel stage an untrained one
  and splatted input occupancy (core.models.egomotion_refine: plain geometric alignment), `--coarse-only`
  drops a bundle's stage, `--untrained-refine` resets its learned parts (confidence 1, gain at init);
- `--floors`: where Gauss-Newton dense alignment (core.models.egomotion_refine.gauss_newton_refine, a
  σ 1.5 then σ 0.7 voxel blur, Cauchy weights) of fixed volumes ends, started from the truth (its bias:
  how far the alignment's optimum lies from the true pose) and from the identity: binary occupancy, the
  area-weighted trilinear splat of the points summed over the views, its max over the views, and the
  latter clamped to 1 (= the "splat" input occupancy); and the same with the query made from frame 0's
  OWN points moved by the true motion (no change of viewpoint: what discretisation alone costs).

Measured (small preset, /work/main/out/diag test split = 16 records of seed 1, 8 moving-camera pairs,
true motion 0.012 rad / 0.81 m; one thread): see README "Egomotion" and core/models/egomotion_refine.py.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from core.baselines.icp import icp_coarse_to_fine
from core.bundle import load_bundle
from core.data.shards import ShardDataset
from core.eval.egomotion_metrics import relative_pose_errors
from core.eval.moving_protocol import camera_setting
from core.eval.protocols.egomotion import _cloud, icp_gates
from core.eval.protocols.inputs import pair_inputs, record_batch
from core.geometry import se3
from core.geometry.camera import depth_to_points
from core.geometry.poses import relative, rig_cam_T_ref
from core.geometry.splat import surface_splat
from core.geometry.voxelize import voxelize
from core.models.egomotion_inputs import egomotion_input_volume
from core.models.egomotion_refine import FeatureMetricRefiner, gauss_newton_refine, gaussian_blur3d

LEVELS = ((1.5, 0.2, 2), (0.7, 0.1, 6))  # the floors' schedule: converged (more iterations than the module's)


def view_points(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor):
    """depth 1×V×H×W, pix_T_cam/cam_T_ref 1×V×4×4 -> (xyz_cam V×N×3, valid V×N, xyz_ref V×N×3)."""
    _, V, H, W = depth.shape
    xyz_cam, valid = depth_to_points(depth.reshape(V, H, W), pix_T_cam.reshape(V, 4, 4))
    return xyz_cam, valid, se3.apply(se3.invert(cam_T_ref.reshape(V, 4, 4)), xyz_cam)


def splat_views(xyz_cam, valid, pix_T_cam, cam_T_ref, grid, fuse: str) -> torch.Tensor:
    """Per-view surface splats (core.geometry.splat.surface_splat) fused by max or sum: 1×1×Z×Y×X."""
    V = xyz_cam.shape[0]
    vol = surface_splat(xyz_cam, valid, pix_T_cam.reshape(V, 4, 4), cam_T_ref.reshape(V, 4, 4), grid)
    return vol.amax(0, keepdim=True) if fuse == "max" else vol.sum(0, keepdim=True)


def lattice_oracle(net, index: int, entering: torch.Tensor, gt: torch.Tensor, grid_s) -> torch.Tensor:
    """Best hard (rotation candidate, integer displacement) update of scale `index`: P×4×4."""
    cands = getattr(net, f"candidates_{index}").double()  # R×4×4
    lim = torch.tensor(net.radius, dtype=torch.float64)  # (x, y, z)
    v = grid_s.voxel_size
    best, best_score = None, None
    for i in range(cands.shape[0]):
        E_i = cands[i] @ entering  # P×4×4
        M = gt @ se3.invert(E_i)  # the left update still needed
        d = torch.maximum(torch.minimum(torch.round(M[:, :3, 3] / v), lim), -lim)
        E = se3.from_rt(torch.eye(3, dtype=torch.float64).expand(E_i.shape[0], 3, 3), d * v) @ E_i
        err = relative_pose_errors(E, gt)
        score = err["rot_err_rad"] * 10 + err["trans_err_m"]
        if best is None:
            best, best_score = E.clone(), score
        else:
            take = score < best_score
            best[take], best_score = E[take], torch.where(take, score, best_score)
    return best


def fmt(est: torch.Tensor, gt: torch.Tensor) -> str:
    err = relative_pose_errors(est, gt)
    return f"R {float(err['rot_err_rad'].mean()):.5f} rad  t {float(err['trans_err_m'].mean()):.4f} m"


def align(r: torch.Tensor, q: torch.Tensor, start: torch.Tensor, grid) -> torch.Tensor:
    E = start
    for sigma, robust, iterations in LEVELS:
        E, _ = gauss_newton_refine(gaussian_blur3d(r, sigma), gaussian_blur3d(q, sigma), E, grid,
                                   iterations=iterations, robust_scale=robust, max_step=(0.05, 1.0))
    return E


def floors(pairs: list[dict], gt: torch.Tensor, grid) -> None:
    print("\nGauss-Newton dense alignment of fixed volumes (bias = from the truth):")
    kinds = {"binary occupancy": lambda xc, v, xr, p, c: voxelize(xr.reshape(1, -1, 3), grid, v.reshape(1, -1)),
             "splat, summed views": lambda xc, v, xr, p, c: splat_views(xc, v, p, c, grid, "sum"),
             "splat, max over views": lambda xc, v, xr, p, c: splat_views(xc, v, p, c, grid, "max"),
             "splat, max, clamped 1": lambda xc, v, xr, p, c: splat_views(xc, v, p, c, grid, "max").clamp(max=1)}
    I = torch.eye(4, dtype=torch.float64).expand_as(gt)
    for name, make in kinds.items():
        vols, self_vols = [], []
        for p in pairs:
            inp = p["inp"]
            xc0, v0, xr0 = view_points(inp["depth0"], inp["pix_T_cam0"], p["c0"])
            xc1, v1, xr1 = view_points(inp["depth1"], inp["pix_T_cam1"], p["c1"])
            r = make(xc0, v0, xr0, inp["pix_T_cam0"], p["c0"]).double()
            q = make(xc1, v1, xr1, inp["pix_T_cam1"], p["c1"]).double()
            vols.append((r, q))
            # frame 0's own points seen from ref1 (moved by the true motion): cam_T_ref1 = cam_T_ref0 · gt
            c_moved = p["c0"] @ p["gt"].float()[:, None]
            xr_moved = se3.apply(se3.invert(p["gt"].float()).expand(xr0.shape[0], 4, 4), xr0)
            self_vols.append((r, make(xc0, v0, xr_moved, inp["pix_T_cam0"], c_moved).double()))
        rows = []
        for label, vs in (("real pairs", vols), ("own points moved", self_vols)):
            for start_name, starts in (("truth", gt), ("identity", I)):
                est = torch.cat([align(r, q, starts[k:k + 1], grid) for k, (r, q) in enumerate(vs)])
                rows.append(f"{label} from {start_name}: {fmt(est, gt)}")
        print(f"  {name}:\n    " + "\n    ".join(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--bundle", action="append", default=[])
    ap.add_argument("--all-pairs", action="store_true")
    ap.add_argument("--attach-refine", action="store_true")
    ap.add_argument("--coarse-only", action="store_true")
    ap.add_argument("--untrained-refine", action="store_true")
    ap.add_argument("--floors", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-icp", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ds = ShardDataset(args.data)
    records = [ds[i] for i in range(len(ds))]
    if not args.all_pairs:
        records = [r for r in records if r["rgb"].shape[0] > 1 and camera_setting(r, 0) == "moving"]
    from core.presets import get_preset
    grid = get_preset(ds.manifest["preset"]).grid
    pairs = []
    for rec in records:
        batch = record_batch(rec, "cpu")
        T = batch["rgb"].shape[1]
        for t0 in range(max(T - 1, 1)):
            t1 = min(t0 + 1, T - 1)
            inp = pair_inputs(batch, t0, t1)
            pairs.append({"rec": rec, "t0": t0, "t1": t1, "inp": inp,
                          "c0": rig_cam_T_ref(inp["world_T_cam0"], inp["world_T_ref0"]),
                          "c1": rig_cam_T_ref(inp["world_T_cam1"], inp["world_T_ref1"]),
                          "gt": relative(inp["world_T_ref0"].double(), inp["world_T_ref1"].double())})
    gt = torch.cat([p["gt"] for p in pairs])
    print(f"pairs: {len(pairs)}; true motion: {float(se3.rotation_angle(gt[:, :3, :3]).mean()):.4f} rad, "
          f"{float(gt[:, :3, 3].norm(dim=1).mean()):.3f} m (mean |x| {float(gt[:, 0, 3].abs().mean()):.3f}, "
          f"|y| {float(gt[:, 1, 3].abs().mean()):.3f}, |z| {float(gt[:, 2, 3].abs().mean()):.3f})")
    print(f"identity: {fmt(torch.eye(4, dtype=torch.float64).expand_as(gt), gt)}")
    if not args.no_icp:
        icps = []
        for p in pairs:
            src, tgt = _cloud(p["rec"], p["t1"], np.eye(4), grid), _cloud(p["rec"], p["t0"], np.eye(4), grid)
            res = icp_coarse_to_fine(src, tgt, iterations=30, max_distances=icp_gates(grid.voxel_size))
            icps.append(torch.from_numpy(res.target_T_source)[None])
        print(f"icp: {fmt(torch.cat(icps), gt)}")
    for path in args.bundle:
        net = load_bundle(path, "cpu").modules["egomotion"].eval()
        if args.attach_refine and net.refiner is None:
            net.refiner, net.input_occupancy = FeatureMetricRefiner(feature_dim=net.feature_dim).eval(), "splat"
        if args.untrained_refine and net.refiner is not None:  # ablation: the stage's learned parts at init
            net.refiner = FeatureMetricRefiner(feature_dim=net.feature_dim, **net.refiner.config()).eval()
        if args.coarse_only:
            net.refiner = None
        print(f"\n== {path}  (scales {net.scales}, input occupancy {net.input_occupancy}, "
              f"sub-voxel stage {'on' if net.refiner is not None else 'off'})")
        outs, ms, ms_vol = [], [], []
        with torch.no_grad():
            for p in pairs:
                inp = p["inp"]
                t = time.perf_counter()
                v0 = egomotion_input_volume(net, inp["rgb0"], inp["depth0"], inp["pix_T_cam0"], p["c0"])
                ms_vol.append((time.perf_counter() - t) * 1000)
                v1 = egomotion_input_volume(net, inp["rgb1"], inp["depth1"], inp["pix_T_cam1"], p["c1"])
                net(v0, v1)  # warm-up
                t = time.perf_counter()
                outs.append(net(v0, v1))
                ms.append((time.perf_counter() - t) * 1000)
        final = torch.cat([o["ref0_T_ref1"].double() for o in outs])
        per_scale = torch.cat([o["per_scale"].double() for o in outs], dim=1)  # S×P×4×4
        print(f"forward {np.median(ms):.1f} ms/pair, one input volume {np.median(ms_vol):.1f} ms "
              f"(median, {args.threads} thread(s))")
        entering = torch.eye(4, dtype=torch.float64).expand_as(gt)
        for i, s in enumerate(net.scales):
            g = net.scale_grid(s)
            print(f"  scale {s} ({g.voxel_size:.2f} m voxels): module {fmt(per_scale[i], gt)}; integer oracle "
                  f"from the estimate entering it {fmt(lattice_oracle(net, i, entering, gt, g), gt)}")
            entering = per_scale[i]
        if net.refiner is not None:
            print(f"  sub-voxel stage: {fmt(final, gt)}")
        print(f"  final: {fmt(final, gt)}")
        diff = (se3.invert(gt) @ final)[:, :3, 3]
        print(f"  final translation error per axis (mean |.|): x {float(diff[:, 0].abs().mean()):.3f} "
              f"y {float(diff[:, 1].abs().mean()):.3f} z {float(diff[:, 2].abs().mean()):.3f} m")
    if args.floors:
        floors(pairs, gt, grid)


if __name__ == "__main__":
    main()
