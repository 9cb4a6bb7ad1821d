"""Brief in-process training of egomotion, 3D flow and occupancy on a tiny generated dataset; prints the
held-out figures against their baselines (identity egomotion, zero-motion flow).

    python tests/benchmarks/bench_issue4_training.py [--ego-steps 150] [--flow-steps 150] [--occ-steps 60]

Data: `tiny` preset records from core.synthetic.generate_record with a moving ego (T = 2), train seeds
1000+, held-out seeds 0+. Flow is trained over a FROZEN, RANDOMLY INITIALISED mapper (no pretraining in
this bench), so its figures are a floor, not the paper's setting. Egomotion is trained with its default
yaw-heavy augmentation and evaluated on the held-out pairs' true ego motion, with and without a
±6°/±1 m perturbation.
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from core.data.batch import records_to_batch
from core.data.ground_truth import gt_flow
from core.eval.egomotion_metrics import relative_pose_errors
from core.eval.flow_metrics import add_sums, flow_error_sums, flow_scores
from core.presets import TINY
from core.synthetic.generate import generate_record
from core.tasks.egomotion import EgomotionTask, random_perturbation
from core.tasks.flow import FlowTask
from core.tasks.occupancy import OccupancyTask
from core.tasks.poses import cam_T_ref, ref0_T_ref1
from core.models.egomotion_inputs import fused_input_volume


def records(seeds):
    return [generate_record(TINY, seed=s, moving_ego=True) for s in seeds]


def train(task, data, steps: int, batch_size: int, lr: float, label: str) -> float:
    opt = torch.optim.Adam([p for p in task.parameters() if p.requires_grad], lr=lr)
    task.train()
    start = time.time()
    for step in range(steps):
        i = (step * batch_size) % len(data)
        batch = records_to_batch([data[(i + k) % len(data)] for k in range(batch_size)])
        out = task(batch)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        if step % max(1, steps // 5) == 0 or step == steps - 1:
            shown = ", ".join(f"{k}={float(v):.3f}" for k, v in out.items())
            print(f"  [{label}] step {step + 1}/{steps}: {shown}", flush=True)
    return time.time() - start


@torch.no_grad()
def eval_egomotion(task, data, perturb: bool, seed: int = 0):
    task.eval()
    gen = torch.Generator().manual_seed(seed)
    est, gts = [], []
    for rec in data:
        b = records_to_batch([rec])
        cam0, cam1 = cam_T_ref(b, 0, 0), cam_T_ref(b, 1, 1)
        gt = ref0_T_ref1(b, 0, 1)
        if perturb:
            P = random_perturbation(1, max_deg=6.0, max_m=1.0, generator=gen)
            cam1, gt = cam1 @ P[:, None], gt @ P
        g = task.cfg.grid
        v0 = fused_input_volume(b["rgb"][:, 0], b["depth"][:, 0], b["pix_T_cam"], cam0, g)
        v1 = fused_input_volume(b["rgb"][:, 1], b["depth"][:, 1], b["pix_T_cam"], cam1, g)
        est.append(task.egomotion(v0, v1)["ref0_T_ref1"])
        gts.append(gt)
    est, gts = torch.cat(est), torch.cat(gts)
    model = relative_pose_errors(est, gts)
    ident = relative_pose_errors(torch.eye(4).expand_as(gts), gts)
    return {k: (float(model[k].mean()), float(ident[k].mean())) for k in ("rot_err_deg", "trans_err_m")}


@torch.no_grad()
def eval_flow(task, data):
    task.eval()
    sums = {"model": {}, "zero": {}}
    for rec in data:
        b = records_to_batch([rec])
        f0, f1 = task.stabilised_maps(b, 0)
        pred = task.flow(f0, f1)["flow"]
        gt = gt_flow(rec, 0, TINY.grid)[None]
        sums["model"] = add_sums(sums["model"], flow_error_sums(pred, gt))
        sums["zero"] = add_sums(sums["zero"], flow_error_sums(torch.zeros_like(gt), gt))
    return {k: flow_scores(v) for k, v in sums.items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--ego-steps", type=int, default=150)
    ap.add_argument("--flow-steps", type=int, default=150)
    ap.add_argument("--occ-steps", type=int, default=60)
    ap.add_argument("--train-records", type=int, default=24)
    ap.add_argument("--test-records", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    t = time.time()
    train_data = records(range(1000, 1000 + args.train_records))
    test_data = records(range(args.test_records))
    print(f"generated {len(train_data)} train + {len(test_data)} test tiny records in {time.time() - t:.1f}s")

    ego = EgomotionTask.from_preset(TINY, seed=0)
    secs = train(ego, train_data, args.ego_steps, 2, 1e-3, "egomotion")
    for perturb in (False, True):
        r = eval_egomotion(ego, test_data, perturb)
        print(f"EGOMOTION ({args.ego_steps} steps × batch 2, {secs:.0f}s; held-out, perturbed={perturb}): "
              f"rot {r['rot_err_deg'][0]:.3f}° vs identity {r['rot_err_deg'][1]:.3f}°, "
              f"trans {r['trans_err_m'][0]:.3f} m vs identity {r['trans_err_m'][1]:.3f} m")

    flow = FlowTask.from_preset(TINY, seed=0)
    secs = train(flow, train_data, args.flow_steps, 1, 1e-3, "flow")
    s = eval_flow(flow, test_data)
    print(f"FLOW ({args.flow_steps} steps × batch 1, {secs:.0f}s; held-out L1 EPE voxels, no occupancy mask): "
          f"model full {s['model']['epe_l1_full']:.3f} static {s['model']['epe_l1_static']:.3f} "
          f"moving {s['model']['epe_l1_moving']:.3f} | zero-motion full {s['zero']['epe_l1_full']:.3f} "
          f"static {s['zero']['epe_l1_static']:.3f} moving {s['zero']['epe_l1_moving']:.3f} "
          f"({s['zero']['voxels_moving']} moving voxels)")

    occ = OccupancyTask.from_preset(TINY, seed=0)
    secs = train(occ, train_data, args.occ_steps, 1, 1e-3, "occupancy")
    occ.eval()
    with torch.no_grad():
        accs = [occ(records_to_batch([r])) for r in test_data]
    mean = {k: sum(float(a[k]) for a in accs) / len(accs) for k in ("acc_occupied", "acc_free", "acc_all", "iou_occupied")}
    print(f"OCCUPANCY ({args.occ_steps} steps × batch 1, {secs:.0f}s; held-out mean per record): "
          + ", ".join(f"{k} {v:.3f}" for k, v in mean.items()))


if __name__ == "__main__":
    main()
