"""The inference routes over `core.pipeline`: what each needs, how requests batch, one batched call.

Transports (REST, gRPC) decode and validate into `validation.Views`, build a route's input with the
constructors here (which refuse, naming the field, what a route cannot answer without guessing), and
`await runtime.infer(route, input)`. Every route runs a whole batch of requests as one `core.pipeline`
call (inputs stacked along B) and splits the outputs back per request. The converters between validated
numpy inputs and pipeline tensors (`views_tensors`, `pair_tensors`, `detections_results`) live here
only; the stream step (camera_stream.py) uses them too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Hashable, Sequence

import numpy as np
import torch

from core.pipeline import detect, estimate_egomotion, estimate_flow, map_frames, moving_objects
from core.pipeline.moving_boxes import DEFAULT_DT, MovingObjectsConfig
from core.pipeline.stabilise import STABILISE
from services.inference.errors import InvalidInput
from services.inference.validation import Views, check_pair, pair_interval, require_poses

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
class FlowInput:
    views0: Views
    views1: Views
    stabilise: str = "poses"          # core.pipeline.stabilise: "egomotion" | "poses" | "none"


@dataclass(frozen=True)
class DetectInput:
    views: Views
    min_score: float = 0.0


@dataclass(frozen=True)
class MovingInput:
    views0: Views
    views1: Views
    min_score: float = -1.0           # saliency scores lie in [−1, 1]: the default keeps every box
    dt: float = DEFAULT_DT            # seconds from views0 to views1 (validation.pair_interval)
    # the post-processing (the runtime's, RuntimeConfig.moving_objects: the same for every request, so a
    # batch shares it)
    config: MovingObjectsConfig = MovingObjectsConfig()


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


def _no_extra(item) -> tuple[str, ...]:
    return ()


@dataclass(frozen=True)
class Route:
    """One inference route: the bundle modules it needs and its batched runner."""

    name: str
    modules: tuple[str, ...]          # bundle modules every request needs
    batch_key: Callable[[Any], Hashable]
    run: Callable[[Any, list, torch.device], list]  # (bundle, inputs, device) -> results
    extra_modules: Callable[[Any], tuple[str, ...]] = _no_extra  # what one request's options add

    def needs(self, item: Any | None = None) -> tuple[str, ...]:
        return self.modules if item is None else self.modules + self.extra_modules(item)


# ------------------------------------------------------------------------------ inputs


def pair_input(views0: Views, views1: Views) -> PairInput:
    check_pair(views0, views1, "views1")
    return PairInput(views0=views0, views1=views1)


def flow_input(views0: Views, views1: Views, stabilise: str) -> FlowInput:
    """stabilise: "egomotion" (the bundle's estimate), "poses" (the views' world_T_cam, which must then be
    given) or "none" (the flow carries the camera's motion)."""
    check_pair(views0, views1, "views1")
    if stabilise not in STABILISE:
        raise InvalidInput("stabilise", f"must be one of {', '.join(STABILISE)}, got {stabilise!r}")
    if stabilise == "poses":
        for name, views in (("views0", views0), ("views1", views1)):
            require_poses(views, f"{name}[0].world_T_cam", "stabilise=poses brings the second instant into the first with the "
                                       "cameras' poses; send both instants' world_T_cam, or stabilise=egomotion | none")
    return FlowInput(views0=views0, views1=views1, stabilise=stabilise)


def moving_interval(views0: Views, views1: Views, *, modules: Sequence[str], frame_dt: float,
                    pose_fields: tuple[str, str] = ("views0[0].world_T_cam", "views1[0].world_T_cam"),
                    time_field: str = "views1") -> float:
    """Seconds from views0 to views1 (validation.pair_interval: from their capture times, else timestamps), after refusing what a
    moving-object pair cannot answer without guessing: a bundle without an egomotion module (`modules`: the
    bundle's) stabilises with the poses, which must then be given. The stream step checks its pairs here too."""
    if "egomotion" not in modules:
        for views, field in zip((views0, views1), pose_fields):
            require_poses(views, field, "this bundle has no egomotion module, so moving objects are stabilised "
                                        "with the cameras' poses; send both instants' world_T_cam")
    return pair_interval(views0, views1, frame_dt=frame_dt, field1=time_field)


def moving_input(views0: Views, views1: Views, *, min_score: float, frame_dt: float,
                 modules: Sequence[str], config: MovingObjectsConfig) -> MovingInput:
    check_pair(views0, views1, "views1")
    return MovingInput(views0=views0, views1=views1, min_score=min_score,
                       dt=moving_interval(views0, views1, modules=modules, frame_dt=frame_dt),
                       config=config)


# ------------------------------------------------------------------------------ converters


def views_tensors(views: Sequence[Views], device: torch.device) -> dict[str, torch.Tensor]:
    """B requests' Views -> rgb B×V×3×H×W in [0,1], depth B×V×H×W, pix_T_cam / world_T_cam B×V×4×4."""
    rgb = torch.from_numpy(np.stack([v.rgb for v in views])).to(device)  # B×V×H×W×3 uint8
    rgb = rgb.permute(0, 1, 4, 2, 3).float().div_(255.0)                # B×V×3×H×W
    return {
        "rgb": rgb,
        "depth": torch.from_numpy(np.stack([v.depth for v in views])).to(device),          # B×V×H×W
        "pix_T_cam": torch.from_numpy(np.stack([v.pix_T_cam for v in views])).to(device),  # B×V×4×4
        "world_T_cam": torch.from_numpy(np.stack([v.world_T_cam for v in views])).to(device),
    }


def pair_tensors(views0: Sequence[Views], views1: Sequence[Views], device) -> dict[str, torch.Tensor]:
    """B pairs -> the pair keywords of core.pipeline (rgb0, depth0, ..., world_T_cam1), batched as above."""
    t0, t1 = views_tensors(views0, device), views_tensors(views1, device)
    return {**{f"{k}0": v for k, v in t0.items()}, **{f"{k}1": v for k, v in t1.items()}}


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


def detections_results(out: dict[str, torch.Tensor], min_scores: Sequence[float], *,
                       label: str) -> list[DetectionsResult]:
    """Pipeline boxes B×K×7, scores B×K, valid B×K (, velocities B×K×3) -> per item the valid rows scored
    at least its min score, best first (velocities zero where the pipeline gives none)."""
    boxes, scores = _numpy(out["boxes"]), _numpy(out["scores"])
    valid = out["valid"].cpu().numpy().astype(bool)
    vel = _numpy(out["velocities"]) if "velocities" in out else np.zeros(boxes.shape[:2] + (3,), np.float32)
    results = []
    for b, min_score in enumerate(min_scores):
        keep = valid[b] & (scores[b] >= min_score)
        order = np.argsort(-scores[b][keep], kind="stable")
        results.append(DetectionsResult(boxes=boxes[b][keep][order], scores=scores[b][keep][order],
                                        velocities=vel[b][keep][order], labels=[label] * int(keep.sum())))
    return results


# ------------------------------------------------------------------------------ runners


def _run_map(bundle, inputs: list[MapInput], device) -> list[MapResult]:
    out = map_frames(bundle, **views_tensors([i.views for i in inputs], device))
    observed = _numpy(out["observed"])                                 # B×1×Z×Y×X
    occupancy = _numpy(out["occupancy"]) if "occupancy" in out else None  # B×1×Z×Y×X
    heightmap = _numpy(out["heightmap"]) if "heightmap" in out else None  # B×Z×X
    features = _numpy(out["features"]) if any(i.features for i in inputs) else None  # B×F×Z×Y×X
    return [MapResult(observed=observed[b, 0], occupancy=None if occupancy is None else occupancy[b, 0],
                      heightmap=None if heightmap is None else heightmap[b],
                      features=features[b] if item.features else None)
            for b, item in enumerate(inputs)]


def _pairs(inputs: list, device) -> dict[str, torch.Tensor]:
    return pair_tensors([i.views0 for i in inputs], [i.views1 for i in inputs], device)


def _run_egomotion(bundle, inputs: list[PairInput], device) -> list[EgomotionResult]:
    out = _numpy(estimate_egomotion(bundle, **_pairs(inputs, device))["cam0_T_cam1"])  # B×4×4
    return [EgomotionResult(cam0_T_cam1=out[b]) for b in range(len(inputs))]


def _run_flow(bundle, inputs: list[FlowInput], device) -> list[FlowResult]:
    # one stabilisation per batch: it is part of the batch key
    out = _numpy(estimate_flow(bundle, **_pairs(inputs, device), stabilize=inputs[0].stabilise)["flow"])  # B×3×Z×Y×X
    return [FlowResult(flow=out[b]) for b in range(len(inputs))]


def _run_detect(bundle, inputs: list[DetectInput], device) -> list[DetectionsResult]:
    out = detect(bundle, **views_tensors([i.views for i in inputs], device), min_score=min(i.min_score for i in inputs))
    return detections_results(out, [i.min_score for i in inputs], label="object")


def _run_moving(bundle, inputs: list[MovingInput], device) -> list[DetectionsResult]:
    out = moving_objects(bundle, **_pairs(inputs, device), dt=[i.dt for i in inputs], config=inputs[0].config)
    return detections_results(out, [i.min_score for i in inputs], label="moving")


ROUTES: dict[str, Route] = {r.name: r for r in (
    Route("map", ("mapper",), lambda i: ("map", i.views.shape_key, i.features), _run_map),
    Route("egomotion", ("egomotion",), lambda i: ("egomotion", i.views0.shape_key), _run_egomotion),
    Route("flow", ("mapper", "flow"), lambda i: ("flow", i.views0.shape_key, i.stabilise), _run_flow,
          extra_modules=lambda i: ("egomotion",) if i.stabilise == "egomotion" else ()),
    Route("detect", ("mapper", "detector"), lambda i: ("detect", i.views.shape_key), _run_detect),
    Route("moving_objects", ("mapper", "flow"), lambda i: ("moving_objects", i.views0.shape_key), _run_moving),
)}
