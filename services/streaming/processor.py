"""The bridge's frame processor over the shared inference runtime's loaded bundle.

Decoding and validation are the gRPC transport's own (`services.inference.wire.view_from_proto`),
so a frame is accepted on zenoh exactly when it would be accepted by the Frame RPCs. Each frame
after a camera's first runs one `core.pipeline.moving_step` on the bridge's worker thread: egomotion
once (previous → current; the camera-to-camera motion is published on `n3dmap/<camera>/egomotion`)
and the egomotion-stabilised 3D flow → moving objects, whose boxes are published in the frame
`ref` = the camera at the previous frame, with `world_T_frame` naming that pose. The answers equal
the runtime's `egomotion` and `moving_objects` routes (tests/unit/streaming/test_stream_step.py).

Per camera, `CameraState.extra` keeps what the previous frame contributes to the next step (its
egomotion input volume, feature map and occupancy in its own ref), keyed by its sequence number and
the bundle version, so a hot reload or a reset never mixes stale tensors in. `prepare` fills that
cache while the bridge waits for the next frame, which takes the map of the previous frame off the
next frame's latency.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np
import torch
from google.protobuf.message import DecodeError

from core.moving.amodal import SizePrior
from core.pipeline.moving import DEFAULT_DT, MovingObjectsConfig
from core.pipeline.stream_step import FrameEncoding, encode_previous, moving_step
from n3dmap.v1 import inference_pb2, types_pb2
from services.inference import codecs
from services.inference.errors import InvalidInput
from services.inference.routes import BOX_FRAME, DetectionsResult
from services.inference.runtime import Runtime
from services.inference.validation import View, Views, stack_views
from services.inference.wire import detections_proto, view_from_proto
from services.streaming.bridge import CameraState, MalformedFrame, Outputs

STAGE_WINDOW = 512  # per-stage timings kept for the status percentiles


def views_tensors(views: Views, device: torch.device) -> dict[str, torch.Tensor]:
    """One instant's Views -> rgb 1×V×3×H×W in [0,1], depth 1×V×H×W, pix_T_cam/world_T_cam 1×V×4×4
    (as the inference routes convert them)."""
    rgb = torch.from_numpy(views.rgb[None]).to(device)            # 1×V×H×W×3 uint8
    rgb = rgb.permute(0, 1, 4, 2, 3).float().div_(255.0)           # 1×V×3×H×W
    return {"rgb": rgb, "depth": torch.from_numpy(views.depth[None]).to(device),  # 1×V×H×W
            "pix_T_cam": torch.from_numpy(views.pix_T_cam[None]).to(device),    # 1×V×4×4
            "world_T_cam": torch.from_numpy(views.world_T_cam[None]).to(device)}


def detections_result(out: dict, *, min_score: float) -> DetectionsResult:
    """moving_step's padded boxes of item 0 -> DetectionsResult (valid rows with score ≥ min_score,
    best first), as the moving_objects route splits them."""
    boxes = out["boxes"][0].float().cpu().numpy()             # K×7
    scores = out["scores"][0].float().cpu().numpy()           # K
    velocities = out["velocities"][0].float().cpu().numpy()   # K×3
    keep = out["valid"][0].cpu().numpy().astype(bool) & (scores >= min_score)
    order = np.argsort(-scores[keep], kind="stable")
    return DetectionsResult(boxes=boxes[keep][order], scores=scores[keep][order], velocities=velocities[keep][order],
                            labels=["moving"] * int(keep.sum()))


class RuntimeProcessor:
    """Decode `Frame` payloads and run egomotion + moving objects on the runtime's bundle."""

    def __init__(self, runtime: Runtime, *, min_score: float = 0.0, reuse: bool = True,
                 frame_dt: float = DEFAULT_DT, size_prior: SizePrior | None = None) -> None:
        """size_prior: amodal boxes of this object size (core.moving.amodal), or None for visible boxes."""
        missing = [r for r in ("moving_objects",) if r not in runtime.routes]
        if missing:
            raise ValueError(f"bundle {runtime.version} cannot serve the stream bridge: it lacks the modules for "
                             f"{', '.join(missing)} (loaded modules: {', '.join(runtime.modules)}); "
                             "train the flow module into the bundle first")
        self.runtime = runtime
        self.min_score = min_score
        if not frame_dt > 0:
            raise ValueError(f"frame_dt must be positive seconds, got {frame_dt}")
        self.frame_dt = float(frame_dt)  # seconds between consecutive sequence numbers of a camera
        self.reuse = reuse  # False: encode the previous frame again every step (for comparisons)
        self.size_prior = size_prior
        self._stages: dict[str, deque] = {}
        self._stages_lock = threading.Lock()

    # -- decoding ---------------------------------------------------------------------------------
    def decode(self, payload: bytes) -> View:
        msg = types_pb2.Frame()
        try:
            msg.ParseFromString(payload)
        except DecodeError as e:
            raise MalformedFrame(f"payload is not an n3dmap.v1.Frame: {e}") from None
        try:
            return view_from_proto(msg, "frame")
        except InvalidInput as e:
            raise MalformedFrame(str(e)) from None

    # -- the per-camera cache ----------------------------------------------------------------------
    def _cached(self, state: CameraState, sequence: int, version: str) -> FrameEncoding | None:
        extra = state.extra
        if self.reuse and extra.get("sequence") == sequence and extra.get("bundle_version") == version:
            return extra.get("encoding")
        return None

    def _remember(self, state: CameraState, sequence: int, version: str, encoding: FrameEncoding) -> None:
        state.extra.update(sequence=sequence, bundle_version=version, encoding=encoding)

    def prepare(self, camera: str, state: CameraState) -> None:
        """Idle-time work: encode `state.previous` (the last processed frame) for the next step."""
        previous = state.previous
        if not self.reuse or previous is None:
            return
        bundle, version = self.runtime.bundle, self.runtime.version
        cached = self._cached(state, previous.sequence, version)
        if cached is not None and cached.features is not None:
            return
        timings: dict[str, float] = {}
        with torch.inference_mode():
            encoding = encode_previous(bundle, **views_tensors(stack_views([previous], "previous"), self.runtime.device),
                                       cached=cached, timings=timings)
        self._remember(state, previous.sequence, version, encoding)
        self._record({f"idle_{k}": v for k, v in timings.items()})

    # -- one frame -----------------------------------------------------------------------------------
    def process(self, camera: str, state: CameraState, frame: View) -> Outputs:
        started = time.perf_counter()
        wall_started = time.time()
        views1 = stack_views([frame], "frame")
        bundle, version = self.runtime.bundle, self.runtime.version  # one bundle for the whole step
        if state.previous is None or state.previous.depth.shape != frame.depth.shape:
            # First frame of this camera (or its image size changed): nothing to compare with yet.
            state.extra.clear()
            empty = types_pb2.Detections(frame=BOX_FRAME, bundle_version=version, camera_id=camera,
                                         sequence=frame.sequence, source_timestamp=frame.timestamp,
                                         world_T_frame=codecs.numpy_to_tensor(frame.world_T_cam))
            return Outputs(moving_objects=empty.SerializeToString(), egomotion=None)
        views0 = stack_views([state.previous], "previous")
        device = self.runtime.device
        timings: dict[str, float] = {}
        # After drops the pair spans several frame intervals: velocities and the speed threshold use
        # the real span, not one interval (sequence numbers only grow here: duplicates and
        # out-of-order frames never reach process, and a publisher restart resets the state).
        config = MovingObjectsConfig(dt=self.pair_dt(state.previous.sequence, frame.sequence), size_prior=self.size_prior)
        with torch.inference_mode():
            t0, t1 = views_tensors(views0, device), views_tensors(views1, device)
            out = moving_step(bundle, **{f"{k}0": v for k, v in t0.items()}, **{f"{k}1": v for k, v in t1.items()},
                              previous=self._cached(state, state.previous.sequence, version), config=config,
                              timings=timings)
        # This frame's own-ref work (its egomotion volume) is the next step's previous-frame cache.
        self._remember(state, frame.sequence, version, out["current"])
        egomotion = None
        if "cam0_T_cam1" in out:
            egomotion = inference_pb2.EgomotionResponse(
                info=inference_pb2.ResponseInfo(bundle_version=version, frame=BOX_FRAME),
                cam0_T_cam1=codecs.numpy_to_tensor(out["cam0_T_cam1"][0].float().cpu().numpy())).SerializeToString()
        moving = detections_result(out, min_score=self.min_score)
        # Boxes are in ref = the camera at the previous frame; sequence/timestamp name the newest frame.
        detections = detections_proto(moving, frame=BOX_FRAME, bundle_version=version, views=views0,
                                      latency_s=time.time() - wall_started)
        detections.sequence = frame.sequence
        detections.source_timestamp = frame.timestamp
        detections.camera_id = camera
        timings["step_total"] = time.perf_counter() - started
        self._record(timings)
        return Outputs(moving_objects=detections.SerializeToString(), egomotion=egomotion)

    def pair_dt(self, sequence0: int, sequence1: int) -> float:
        """Seconds spanned by frames `sequence0` -> `sequence1` of one camera (at least one interval)."""
        return max(1, int(sequence1) - int(sequence0)) * self.frame_dt

    # -- per-stage timings ---------------------------------------------------------------------------
    def _record(self, timings: dict[str, float]) -> None:
        with self._stages_lock:
            for stage, seconds in timings.items():
                self._stages.setdefault(stage, deque(maxlen=STAGE_WINDOW)).append(1000.0 * seconds)

    def stats(self) -> dict:
        """Per-stage milliseconds over the recent steps: {stage: {p50, p99, mean, count}}."""
        with self._stages_lock:
            snapshot = {k: np.asarray(v, np.float64) for k, v in self._stages.items()}
        return {stage: {"p50": round(float(np.percentile(ms, 50)), 2), "p99": round(float(np.percentile(ms, 99)), 2),
                        "mean": round(float(ms.mean()), 2), "count": int(ms.size)}
                for stage, ms in sorted(snapshot.items()) if ms.size}
