"""2D and 3D patch retrieval P@1/5/10 of a pretraining arm (the paper's appendix, Table "retrieval").

Every (test record, target view) at step 0 is one example; the other views are the inputs, as in
pretraining (core.tasks.pretrain):
- 3D: queries are feature cubes of the map fused from the input views ("top-down"), candidates the
  cubes at the same voxels of the map of the target view alone; centres on voxels the target view
  sees as occupied and the inputs observe;
- 2D: queries are patches of the map rendered into the target camera by the projector, candidates
  the patches at the same pixels of the bottom-up 2D features of the target image (the contrastive
  model's 2D net; for the RGB-regression model, whose projector predicts colour, the target image
  itself); centres on pixels whose depth lands inside the grid.
`core.eval.retrieval.retrieval_pool` draws `per_example` pairs per example and `precision_at_k` ranks
each query against every candidate of the pool (one true match, the rest negatives, many from other
scenes). The random arm is an untrained contrastive model (seeded).
"""

from __future__ import annotations

import math
from typing import Iterable

import torch
import torch.nn.functional as F

from core.eval.retrieval import precision_at_k, retrieval_pool
from core.geometry import se3
from core.geometry.camera import scale_intrinsics
from core.models.latent_map import masked_average
from core.tasks import build_task
from services.cli.eval_tasks.common import record_batch


def pretrain_model(preset, *, arm: str, bundle_dir=None, seed: int = 0) -> torch.nn.Module:
    """The pretraining task of `arm` with the bundle's weights (random arm: seeded fresh weights)."""
    from core.bundle import load_bundle

    torch.manual_seed(seed)
    task = build_task("pretrain", preset, objective="regression" if arm == "regression" else "contrastive")
    if bundle_dir is not None:
        bundle = load_bundle(bundle_dir, "cpu")
        for name, module in task.exported_modules().items():
            if name in bundle.modules:
                module.load_state_dict(bundle.modules[name].state_dict())
    return task.eval()


@torch.no_grad()
def example_features(task, batch: dict, target: int, t: int = 0) -> dict[str, torch.Tensor]:
    """Query/candidate features of one (record, target view): 3D C×Z×Y×X and 2D E×Hr×Wr plus masks."""
    rgb, depth, pix = batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"]  # B×V×3×H×W, B×V×H×W, B×V×4×4
    B, V, _, H, W = rgb.shape
    inputs = [v for v in range(V) if v != target]
    cam_T_ref = se3.compose(se3.invert(batch["world_T_cam"][:, t]),
                            batch["world_T_ref"][:, t, None].expand(B, V, 4, 4))   # B×V×4×4
    feats, in_view, occupied = task.mapper.encode_views(rgb, depth, pix, cam_T_ref)
    top3d = masked_average(feats[:, inputs], in_view[:, inputs])                  # B×F×Z×Y×X
    valid3d = (occupied[:, target] > 0.5) & (in_view[:, inputs].amax(dim=1) > 0.5)  # B×1×Z×Y×X
    scale = task.cfg.render_scale
    Hr, Wr = (math.ceil(H / 2), math.ceil(W / 2)) if scale == 0.5 else (H, W)
    pix_render = scale_intrinsics(pix[:, target], Wr / W, Hr / H)
    top2d = task.projector(top3d, pix_render, cam_T_ref[:, target], Hr, Wr)     # B×E×Hr×Wr
    if task.net2d is not None:
        bottom2d = task.net2d(rgb[:, target].contiguous())                       # B×E×Hr×Wr
    else:  # regression: the projector predicts centred colour; compare with the target image
        bottom2d = F.interpolate(rgb[:, target], size=(Hr, Wr), mode="area") - 0.5  # B×3×Hr×Wr
    valid2d = task._valid_pixels(depth[:, target], pix[:, target], cam_T_ref[:, target], (Hr, Wr)) > 0.5
    return {"q3": top3d[0], "c3": feats[0, target], "v3": valid3d[0, 0],
            "q2": top2d[0], "c2": bottom2d[0], "v2": valid2d[0, 0]}


def evaluate_retrieval(task, records: Iterable[dict], *, device, per_example: int, size: int, seed: int) -> dict:
    """{"2d": {"p@1", "p@5", "p@10"}, "3d": {...}, "pairs_2d", "pairs_3d"} over every (record, view)."""
    task = task.to(device)
    q2, c2, v2, q3, c3, v3 = [], [], [], [], [], []
    for record in records:
        batch = record_batch(record, device)
        for target in range(batch["rgb"].shape[2]):
            f = example_features(task, batch, target)
            # Skip an example without enough centres rather than fail the pool (tiny views may see little).
            if int(_inner(f["v3"], size).sum()) >= per_example:
                q3.append(f["q3"].cpu()), c3.append(f["c3"].cpu()), v3.append(f["v3"].cpu())
            if int(_inner(f["v2"], size).sum()) >= per_example:
                q2.append(f["q2"].cpu()), c2.append(f["c2"].cpu()), v2.append(f["v2"].cpu())
    out: dict = {}
    for name, (q, c, v) in {"2d": (q2, c2, v2), "3d": (q3, c3, v3)}.items():
        if not q:
            out[name] = {"p@1": float("nan"), "p@5": float("nan"), "p@10": float("nan")}
            out[f"pairs_{name}"] = 0
            continue
        gen = torch.Generator().manual_seed(seed)
        queries, candidates = retrieval_pool(q, c, per_example=per_example, size=size, generator=gen, valid=v)
        out[name] = precision_at_k(queries, candidates)
        out[f"pairs_{name}"] = int(queries.shape[0])
    return out


def _inner(valid: torch.Tensor, size: int) -> torch.Tensor:
    """valid with a border of size//2 cleared (where retrieval_pool may draw centres)."""
    m = size // 2
    inner = torch.zeros_like(valid)
    inner[tuple(slice(m, s - m) for s in valid.shape)] = valid[tuple(slice(m, s - m) for s in valid.shape)]
    return inner
