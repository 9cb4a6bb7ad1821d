"""The inference routes over `core.pipeline`: what each needs, how requests batch, one batched call.

This is the only file that calls `core.pipeline`; transports (REST, gRPC, zenoh) and the runtime
see validated numpy inputs (validation.Views) and numpy results. Every route runs a whole batch of
requests as one pipeline call (inputs stacked along B) and splits the outputs back per request.
"""

from __future__ import annotations

import types
from dataclasses import dataclass
from typing import Any, Callable, Hashable

import numpy as np
import torch

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
    min_score: float = -1.0           # saliency scores lie in [−1, 1]: the default keeps every box


@dataclass(frozen=True)
class MapResult:
    observed: np.ndarray              # Z×Y×X float32 in {0, 1}: inside some view's frustum
    occupancy: np.ndarray | None      # Z×Y×X float32 in [0, 1] (bundles with an occupancy head)
    heightmap: np.ndarray | None      # Z×X float32 metres above the grid floor (ref y = ymax); 0 = empty
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
    modules: tuple[str, ...]          # bundle modules it needs
    function: str                     # the core.pipeline function it calls
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


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def pipeline_function(name: str) -> Callable | None:
    """`core.pipeline.<name>` (or from one of its submodules); None if this build lacks it."""
    import importlib

    def function_in(module) -> Callable | None:
        found = getattr(module, name, None)  # `core.pipeline.detect` may be the submodule, not the function
        return found if callable(found) and not isinstance(found, types.ModuleType) else None

    found = function_in(importlib.import_module("core.pipeline"))
    for sub in PIPELINE_SUBMODULES:
        if found is not None:
            break
        try:
            found = function_in(importlib.import_module(f"core.pipeline.{sub}"))
        except ModuleNotFoundError as e:
            if e.name != f"core.pipeline.{sub}":
                raise
    return found


PIPELINE_SUBMODULES = ("map", "egomotion", "flow", "detect", "moving", "moving_objects")


def _run_map(bundle, inputs: list[MapInput], device) -> list[MapResult]:
    out = pipeline_function("map_frames")(bundle, **_views_tensors([i.views for i in inputs], device))
    observed = _numpy(out["observed"])                                 # B×1×Z×Y×X
    occupancy = _numpy(out["occupancy"]) if "occupancy" in out else None  # B×1×Z×Y×X
    heightmap = _numpy(out["heightmap"]) if "heightmap" in out else None  # B×Z×X
    features = _numpy(out["features"]) if any(i.features for i in inputs) else None  # B×F×Z×Y×X
    return [MapResult(observed=observed[b, 0], occupancy=None if occupancy is None else occupancy[b, 0],
                      heightmap=None if heightmap is None else heightmap[b],
                      features=features[b] if item.features else None)
            for b, item in enumerate(inputs)]


def _pair_tensors(inputs: list, device) -> dict[str, torch.Tensor]:
    t0 = _views_tensors([i.views0 for i in inputs], device)
    t1 = _views_tensors([i.views1 for i in inputs], device)
    return {**{f"{k}0": v for k, v in t0.items()}, **{f"{k}1": v for k, v in t1.items()}}


def _run_egomotion(bundle, inputs: list[PairInput], device) -> list[EgomotionResult]:
    out = _numpy(pipeline_function("estimate_egomotion")(bundle, **_pair_tensors(inputs, device))["cam0_T_cam1"])  # B×4×4
    return [EgomotionResult(cam0_T_cam1=out[b]) for b in range(len(inputs))]


def _run_flow(bundle, inputs: list[PairInput], device) -> list[FlowResult]:
    out = _numpy(pipeline_function("estimate_flow")(bundle, **_pair_tensors(inputs, device))["flow"])  # B×3×Z×Y×X
    return [FlowResult(flow=out[b]) for b in range(len(inputs))]


def _split_boxes(out, inputs: list, *, with_velocity: bool) -> list[DetectionsResult]:
    """Pipeline boxes B×K×7, scores B×K, valid B×K (, velocities B×K×3) -> per-request results.

    A per-item list of {"boxes": K_b×7, "scores": K_b[, "velocities": K_b×3]} is accepted too.
    """
    if isinstance(out, (list, tuple)):
        out = _pad_items(out)
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


def _pad_items(items: list[dict]) -> dict[str, torch.Tensor]:
    """Per-item dicts of K_b rows -> zero-padded B×K tensors with a `valid` mask."""
    B, K = len(items), max([len(d["scores"]) for d in items] + [0])
    boxes, scores = torch.zeros(B, K, 7), torch.zeros(B, K)
    valid, velocities = torch.zeros(B, K, dtype=torch.bool), torch.zeros(B, K, 3)
    for b, d in enumerate(items):
        k = len(d["scores"])
        boxes[b, :k] = torch.as_tensor(d["boxes"], dtype=torch.float32).reshape(k, 7)
        scores[b, :k] = torch.as_tensor(d["scores"], dtype=torch.float32)
        valid[b, :k] = True
        if "velocities" in d:
            velocities[b, :k] = torch.as_tensor(d["velocities"], dtype=torch.float32).reshape(k, 3)
    return {"boxes": boxes, "scores": scores, "valid": valid, "velocities": velocities}


def _run_detect(bundle, inputs: list[DetectInput], device) -> list[DetectionsResult]:
    detect = pipeline_function("detect")
    out = detect(bundle, **_views_tensors([i.views for i in inputs], device),
                 min_score=min(i.min_score for i in inputs))
    return _split_boxes(out, inputs, with_velocity=False)


def _run_moving(bundle, inputs: list[MovingInput], device) -> list[DetectionsResult]:
    out = pipeline_function("moving_objects")(bundle, **_pair_tensors(inputs, device))
    return _split_boxes(out, inputs, with_velocity=True)


ROUTES: dict[str, Route] = {r.name: r for r in (
    Route("map", ("mapper",), "map_frames", lambda i: ("map", i.views.shape_key, i.features), _run_map),
    Route("egomotion", ("egomotion",), "estimate_egomotion", lambda i: ("egomotion", i.views0.shape_key),
          _run_egomotion),
    Route("flow", ("mapper", "flow"), "estimate_flow", lambda i: ("flow", i.views0.shape_key), _run_flow),
    Route("detect", ("mapper", "detector"), "detect", lambda i: ("detect", i.views.shape_key), _run_detect),
    Route("moving_objects", ("mapper", "flow"), "moving_objects", lambda i: ("moving_objects", i.views0.shape_key),
          _run_moving),
)}
