"""The inference routes over `core.pipeline`: what each needs, how requests batch, one batched call.

This is the only file that calls `core.pipeline`; transports (REST, gRPC, zenoh) and the runtime
see validated numpy inputs (validation.Views) and numpy results. Every route runs a whole batch of
requests as one pipeline call (inputs stacked along B) and splits the outputs back per request.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Hashable

import numpy as np
import torch

from core.geometry.grid import GridConfig
from services.inference.validation import Views

BOX_FRAME = "ref"  # boxes, volumes and poses of every answer live in `ref` = camera of views[0]


@dataclass(frozen=True)
class MapInput:
    views: Views
    features: bool = False


@dataclass(frozen=True)
class PairInput:
    views0: Views
    views1: Views


@dataclass(frozen=True)
class DetectInput:
    views: Views
    min_score: float = 0.0


@dataclass(frozen=True)
class MovingInput:
    views0: Views
    views1: Views
    min_score: float = 0.0


@dataclass(frozen=True)
class MapResult:
    occupancy: np.ndarray             # Z×Y×X float32 in [0, 1]
    heightmap: np.ndarray             # Z×X float32 metres (up = −y of ref); NaN where no voxel is occupied
    features: np.ndarray | None       # F×Z×Y×X float32 (when asked)


@dataclass(frozen=True)
class EgomotionResult:
    cam0_T_cam1: np.ndarray           # 4×4 float32


@dataclass(frozen=True)
class FlowResult:
    flow: np.ndarray                  # 3×Z×Y×X float32, voxels, channels (x, y, z)


@dataclass(frozen=True)
class DetectionsResult:
    boxes: np.ndarray                 # K×7 float32 canonical boxes in `ref`
    scores: np.ndarray                # K float32
    velocities: np.ndarray            # K×3 float32 m/s in `ref` (zeros for plain detection)
    labels: list[str]


@dataclass(frozen=True)
class Route:
    """One inference route: the bundle modules it needs and its batched runner."""

    name: str
    modules: tuple[str, ...]
    batch_key: Callable[[Any], Hashable]
    run: Callable[[Any, list, torch.device], list]  # (bundle, inputs, device) -> results


def _views_tensors(views: list[Views], device: torch.device) -> dict[str, torch.Tensor]:
    """B requests' Views -> rgb B×V×3×H×W in [0,1], depth B×V×H×W, pix_T_cam / world_T_cam B×V×4×4."""
    rgb = torch.from_numpy(np.stack([v.rgb for v in views])).to(device)  # B×V×H×W×3 uint8
    rgb = rgb.permute(0, 1, 4, 2, 3).float().div_(255.0)                # B×V×3×H×W
    return {
        "rgb": rgb,
        "depth": torch.from_numpy(np.stack([v.depth for v in views])).to(device),          # B×V×H×W
        "pix_T_cam": torch.from_numpy(np.stack([v.pix_T_cam for v in views])).to(device),  # B×V×4×4
        "world_T_cam": torch.from_numpy(np.stack([v.world_T_cam for v in views])).to(device),
    }


def heightmap_from_occupancy(occupancy: np.ndarray, grid: GridConfig, threshold: float = 0.5) -> np.ndarray:
    """occupancy Z×Y×X -> Z×X height (metres, up = −y of ref) of the top occupied voxel; NaN if none.

    Y points down, so the top occupied voxel of a column is the one with the smallest y index.
    """
    occupied = occupancy > threshold                                   # Z×Y×X
    any_occ = occupied.any(axis=1)                                     # Z×X
    top = np.argmax(occupied, axis=1)                                  # Z×X first (smallest) y index
    y_ref = grid.ymin + (top + 0.5) * grid.voxel_size                  # centre of that voxel in ref
    return np.where(any_occ, -y_ref, np.nan).astype(np.float32)


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def _run_map(bundle, inputs: list[MapInput], device) -> list[MapResult]:
    from core.pipeline import map_frames

    out = map_frames(bundle, **_views_tensors([i.views for i in inputs], device))
    occupancy = _numpy(out["occupancy"])                               # B×1×Z×Y×X
    features = _numpy(out["features"]) if any(i.features for i in inputs) else None  # B×F×Z×Y×X
    grid = bundle.preset.grid
    results = []
    for b, item in enumerate(inputs):
        occ = occupancy[b, 0]                                          # Z×Y×X
        results.append(MapResult(occupancy=occ, heightmap=heightmap_from_occupancy(occ, grid),
                                 features=features[b] if item.features else None))
    return results


def _pair_tensors(inputs: list, device) -> dict[str, torch.Tensor]:
    t0 = _views_tensors([i.views0 for i in inputs], device)
    t1 = _views_tensors([i.views1 for i in inputs], device)
    return {**{f"{k}0": v for k, v in t0.items()}, **{f"{k}1": v for k, v in t1.items()}}


def _run_egomotion(bundle, inputs: list[PairInput], device) -> list[EgomotionResult]:
    from core.pipeline import estimate_egomotion

    out = _numpy(estimate_egomotion(bundle, **_pair_tensors(inputs, device))["cam0_T_cam1"])  # B×4×4
    return [EgomotionResult(cam0_T_cam1=out[b]) for b in range(len(inputs))]


def _run_flow(bundle, inputs: list[PairInput], device) -> list[FlowResult]:
    from core.pipeline import estimate_flow

    out = _numpy(estimate_flow(bundle, **_pair_tensors(inputs, device))["flow"])  # B×3×Z×Y×X
    return [FlowResult(flow=out[b]) for b in range(len(inputs))]


def _split_boxes(out: dict, inputs: list, *, with_velocity: bool) -> list[DetectionsResult]:
    """Pipeline boxes B×K×7, scores B×K, valid B×K (, velocities B×K×3) -> per-request results."""
    boxes, scores = _numpy(out["boxes"]), _numpy(out["scores"])
    valid = out.get("valid")
    valid = valid.cpu().numpy().astype(bool) if valid is not None else np.ones(scores.shape, bool)
    vel = _numpy(out["velocities"]) if with_velocity and "velocities" in out else np.zeros(boxes.shape[:2] + (3,), np.float32)
    results = []
    for b, item in enumerate(inputs):
        keep = valid[b] & (scores[b] >= item.min_score)
        order = np.argsort(-scores[b][keep], kind="stable")
        results.append(DetectionsResult(boxes=boxes[b][keep][order], scores=scores[b][keep][order],
                                        velocities=vel[b][keep][order],
                                        labels=["moving" if with_velocity else "object"] * int(keep.sum())))
    return results


def _run_detect(bundle, inputs: list[DetectInput], device) -> list[DetectionsResult]:
    from core.pipeline import detect

    return _split_boxes(detect(bundle, **_views_tensors([i.views for i in inputs], device)), inputs,
                        with_velocity=False)


def _run_moving(bundle, inputs: list[MovingInput], device) -> list[DetectionsResult]:
    from core.pipeline import moving_objects

    return _split_boxes(moving_objects(bundle, **_pair_tensors(inputs, device)), inputs, with_velocity=True)


ROUTES: dict[str, Route] = {r.name: r for r in (
    Route("map", ("mapper",), lambda i: ("map", i.views.shape_key, i.features), _run_map),
    Route("egomotion", ("mapper", "egomotion"), lambda i: ("egomotion", i.views0.shape_key), _run_egomotion),
    Route("flow", ("mapper", "flow"), lambda i: ("flow", i.views0.shape_key), _run_flow),
    Route("detect", ("mapper", "detector"), lambda i: ("detect", i.views.shape_key), _run_detect),
    Route("moving_objects", ("mapper", "flow"), lambda i: ("moving_objects", i.views0.shape_key), _run_moving),
)}
