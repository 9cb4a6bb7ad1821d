"""Moving objects on a stream of frames, camera by camera: the step the zenoh bridge and the gRPC
StreamMovingObjects share (services.streaming.processor, grpc_server.py).

The transport keeps one `CameraState` per camera and drops duplicate and out-of-order frames
(`CameraState.verdict`). A camera's first frame (or one whose image size changed) has nothing to compare
with and gives empty Detections. Every later frame runs one `core.pipeline.moving_step` between the
previous frame and itself — egomotion once (`cam0_T_cam1`, previous camera to current), stabilised 3D flow,
boxes in `ref` = the camera at the previous frame — with the previous frame's FrameEncoding taken from
`CameraState.extra`, keyed by its sequence number and the bundle's load (version and load generation) so
that a hot reload — even of a bundle replaced in place under the same version — or a reset never mixes
stale tensors in. `prepare` makes that encoding while the transport waits for the next
frame, which takes the map of the previous frame off the next frame's latency. The pair's interval comes
from the frames' capture times, else timestamps ((seq1 − seq0) × `frame_dt` only when neither is given; see
routes.moving_interval). Answers equal the moving_objects route's for the same pair
(tests/unit/streaming/test_stream_step.py).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch

from core.pipeline import encode_previous, moving_step
from core.geometry.poses import level_over_ground, rig_cam_T_ref
from core.pipeline.egomotion import egomotion_from_volumes
from core.pipeline.encoding import FrameEncoding, is_complete
from core.pipeline.moving_boxes import MovingObjectsConfig
from n3dmap.v1 import inference_pb2, types_pb2
from services.inference import codecs
from services.inference.camera_state import CameraState
from services.inference.errors import InvalidInput
from services.inference.routes import BOX_FRAME, detections_results, moving_interval, pair_tensors, views_tensors
from services.inference.validation import View, stack_views
from services.inference.wire import detections_proto

STAGE_WINDOW = 512  # per-stage timings kept for the status percentiles
LEVEL_FRAME = "level"  # the boxes' frame with `level=True`: the previous frame's camera, levelled to gravity


@dataclass(frozen=True)
class AheadEncoding:
    """What `MovingStream.encode_ahead` made of a frame before its step, tagged with the frame and the bundle's
    load (`MovingStream._bundle_now`'s key) so that a step uses it only for that frame and that load (a reload
    never mixes stale tensors in): its own-ref FrameEncoding, and the egomotion from `ego_previous` (the frame expected to
    be its step's previous frame) to it, when that was known."""

    frame: View
    bundle_key: str
    encoding: FrameEncoding
    ego_previous: View | None = None
    ego_estimate: dict | None = None  # core.pipeline.egomotion.egomotion_from_volumes' answer (B = 1)


@dataclass(frozen=True)
class StepAnswer:
    """What one frame gives: its Detections, and the egomotion (previous -> this camera) when the bundle
    has an egomotion module and there was a previous frame."""

    detections: types_pb2.Detections
    egomotion: inference_pb2.EgomotionResponse | None


class MovingStream:
    """Runs the moving-object step of each camera's frames over the runtime's loaded bundle. Call `step`
    and `prepare` from one thread at a time (the bridge's worker, or the runtime's model thread)."""

    def __init__(self, runtime, *, min_score: float, frame_dt: float, objects: MovingObjectsConfig | None = None,
                 reuse: bool = True, level: bool = False, level_ahead: float = 0.0,
                 ground_y: float | None = None) -> None:
        """min_score: boxes scored below it are dropped; frame_dt: seconds per sequence number for frames
        with neither capture times nor timestamps; objects: the moving-object post-processing (its size prior gives amodal boxes,
        core.moving.amodal; None: the defaults, visible boxes); reuse: False encodes the previous frame again every step (for comparisons);
        level: each frame's map frame is its camera levelled to gravity (core.geometry.poses.levelled: the
        frames' world_T_cam must be given, in a world whose Y points down), so boxes are upright and the
        ground is level; the Detections say frame "level" and carry its pose in world_T_frame. Otherwise the
        map frame is the camera itself (frame "ref"). With `level`: level_ahead moves the map frame that many
        metres along the camera's heading, and ground_y (the world's ground plane Y, Y down) puts it the
        bundle preset's `ground_y` above the ground, as the training grids are placed
        (core.geometry.poses.level_over_ground); by default it stays at the camera's centre."""
        if not frame_dt > 0:
            raise ValueError(f"frame_dt must be positive seconds, got {frame_dt}")
        self.runtime = runtime
        self.min_score = min_score
        self.frame_dt = float(frame_dt)
        self.config = objects or MovingObjectsConfig()
        self.reuse = reuse
        self.level = bool(level)
        if not self.level and (level_ahead or ground_y is not None):
            raise ValueError("level_ahead and ground_y place the levelled map frame: they need level=True")
        self.level_ahead = float(level_ahead)
        self.ground_y = None if ground_y is None else float(ground_y)
        self.box_frame = LEVEL_FRAME if self.level else BOX_FRAME
        self._stages: dict[str, deque] = {}
        self._stages_lock = threading.Lock()
        self._warm: set[tuple] = set()  # (bundle load key, image size) pairs already warmed up

    # -- the map frame ------------------------------------------------------------------------------
    def _world_T_ref(self, frame: View) -> torch.Tensor | None:
        """world_T_ref 1×4×4 (on the runtime's device) of `frame`'s map: its camera levelled, or None (the
        camera itself). Raises InvalidInput for a frame without a pose when levelling."""
        if not self.level:
            return None
        if not frame.posed:
            raise InvalidInput("frame.world_T_cam", "missing: levelled boxes need each frame's camera pose in a "
                                                    "gravity-aligned world (Y down); run without levelling to "
                                                    "get boxes in the camera's frame")
        world_T_cam = torch.from_numpy(frame.world_T_cam)[None]  # 1×4×4
        return level_over_ground(world_T_cam, ahead=self.level_ahead, ground_y=self.ground_y,
                                 origin_height=self.runtime.bundle.preset.ground_y).to(self.runtime.device)

    @staticmethod
    def _world_T_frame(frame: View, world_T_ref: torch.Tensor | None) -> np.ndarray:
        """The 4×4 pose in world of `frame`'s map frame (Detections.world_T_frame), given `_world_T_ref(frame)`."""
        return frame.world_T_cam if world_T_ref is None else world_T_ref[0].cpu().numpy()

    # -- the per-camera cache ----------------------------------------------------------------------
    def _bundle_now(self) -> tuple:
        """(bundle, version, cache key) of one load, read at once (a reload swaps the load on another thread).
        The key — the version and the load's generation — is what cached encodings are tagged with: a bundle
        replaced in place and reloaded keeps its version (the run's name), and must not reuse the old weights'
        encodings. Answers carry the version."""
        loaded = self.runtime.loaded
        return loaded.bundle, loaded.version, f"{loaded.version}#{loaded.generation}"

    def _cached(self, state: CameraState, sequence: int, key: str) -> FrameEncoding | None:
        extra = state.extra
        if self.reuse and extra.get("sequence") == sequence and extra.get("bundle_key") == key:
            return extra.get("encoding")
        return None

    def _remember(self, state: CameraState, sequence: int, key: str, encoding: FrameEncoding) -> None:
        state.extra.update(sequence=sequence, bundle_key=key, encoding=encoding)

    def prepare(self, camera: str, state: CameraState) -> None:
        """Idle-time work: encode `state.previous` (the last processed frame) for the next step."""
        previous = state.previous
        if not self.reuse or previous is None:
            return
        bundle, _, key = self._bundle_now()
        cached = self._cached(state, previous.sequence, key)
        if is_complete(cached, bundle):
            return
        timings: dict[str, float] = {}
        tensors = views_tensors([stack_views([previous], "previous")], self.runtime.device)
        with torch.inference_mode():
            encoding = encode_previous(bundle, **tensors, world_T_ref=self._world_T_ref(previous),
                                       cached=cached, fit_ground=self.config.ground_margin is not None, timings=timings)
        self._remember(state, previous.sequence, key, encoding)
        self._record({f"idle_{k}": v for k, v in timings.items()})

    def encode_ahead(self, frame: View, previous: AheadEncoding | None = None) -> AheadEncoding:
        """What of `frame`'s step can be made before the step before it has finished (the bridge runs this
        on a second thread): what the step reads of its frame 1 (the egomotion volume and its encoding)
        and, given `previous` (the look-ahead of the frame the step will most likely pair it with), the
        pair's egomotion. A step uses the egomotion only if its previous frame is that very frame. The rest
        of the frame's own work (its depth evidence, the flow module's encoding, the map), which only the
        step after reads, is left to `prepare` on the worker, which has the time to spare: the two threads
        then carry about equal shares. Safe beside `step`: both only read the bundle."""
        bundle, _, key = self._bundle_now()
        timings: dict[str, float] = {}
        tensors = views_tensors([stack_views([frame], "frame")], self.runtime.device)
        ego_previous, ego_estimate = None, None
        with torch.inference_mode():
            world_T_ref1 = self._world_T_ref(frame)
            encoding = encode_previous(bundle, **tensors, world_T_ref=world_T_ref1, evidence=False, features=False,
                                       flow_encoding=False, timings=timings)
            usable = (previous is not None and not frame.scene_start and previous.bundle_key == key
                      and "egomotion" in bundle.modules
                      and previous.frame.depth.shape == frame.depth.shape
                      and previous.encoding.ego_features is not None and encoding.ego_features is not None)
            if usable:
                started = time.perf_counter()
                # only the previous frame's pose is needed here (its volumes are kept): no image to tensors
                world_T_cam0 = torch.from_numpy(previous.frame.world_T_cam)[None, None]  # 1×1×4×4
                world_T_cam0 = world_T_cam0.to(self.runtime.device)
                ego_estimate = egomotion_from_volumes(
                    bundle.modules["egomotion"], previous.encoding.ego_volume, encoding.ego_volume,
                    rig_cam_T_ref(world_T_cam0, self._world_T_ref(previous.frame)),
                    rig_cam_T_ref(tensors["world_T_cam"], world_T_ref1),
                    features=(previous.encoding.ego_features, encoding.ego_features),
                    fine=(previous.encoding.ego_fine, encoding.ego_fine))
                ego_previous = previous.frame
                timings["egomotion"] = time.perf_counter() - started
        self._record({f"ahead_{k}": v for k, v in timings.items()})
        return AheadEncoding(frame=frame, bundle_key=key, encoding=encoding, ego_previous=ego_previous,
                             ego_estimate=ego_estimate)

    def warm_up(self) -> float:
        """Warm the models up before any frame arrives, for single-view frames of the bundle preset's camera
        size (what `n3dmap stream camera` publishes): a wall of depth 10 m, seen twice. Frames of another
        size warm up on their camera's first frame instead. Returns the seconds it took. Why before: the
        bridge's look-ahead thread makes a frame's encoding while the frame still sits in its camera's slot,
        and a cold first encoding (seconds on a loaded machine) let the second frame replace the first."""
        from core.geometry.camera import intrinsics_from_fov
        from services.inference.validation import make_view

        bundle, _, key = self._bundle_now()
        camera = bundle.preset.camera
        frame = make_view(rgb=np.full((camera.H, camera.W, 3), 128, np.uint8),
                          depth=np.full((camera.H, camera.W), 10.0, np.float32),
                          pix_T_cam=intrinsics_from_fov(camera.H, camera.W, camera.hfov_deg)[0].numpy(),
                          world_T_cam=np.eye(4, dtype=np.float32), field="warm-up")
        started = time.perf_counter()
        self._warm_up(bundle, key, frame)
        if "egomotion" in bundle.modules:  # the look-ahead's own path (encode, then align against a frame)
            self.encode_ahead(frame, self.encode_ahead(frame))
        return time.perf_counter() - started

    def _warm_up(self, bundle, key: str, frame: View) -> None:
        """Run one throwaway pair step (the frame with itself) the first time a bundle meets an image size.
        Why: the first steps pay one-time costs (oneDNN builds its kernels for each new shape, the allocator
        grows its heap); measured at the small preset, the first three answered frames took 187–233 ms
        end to end against a median of 121 ms. A camera's first frame has no pair to answer, so its
        (empty) answer carries that cost instead of the first real answers."""
        warm = (key, tuple(frame.depth.shape))
        with self._stages_lock:
            if warm in self._warm:
                return
            self._warm.add(warm)
        started = time.perf_counter()
        with torch.inference_mode():
            moving_step(bundle, **pair_tensors([stack_views([frame], "frame")], [stack_views([frame], "frame")],
                                               self.runtime.device), config=self.config, dt=self.frame_dt)
        self._record({"warm_up": time.perf_counter() - started})

    # -- one frame -----------------------------------------------------------------------------------
    def step(self, camera: str, state: CameraState, frame: View, ahead: AheadEncoding | None = None) -> StepAnswer:
        """The answer to `frame`, the camera's next frame (state.previous: the one before, or None); `ahead`:
        the frame's `encode_ahead`, when made. Raises InvalidInput when the pair cannot be answered without
        guessing (a clock that does not advance, missing poses a bundle without egomotion needs)."""
        started = time.perf_counter()
        bundle, version, key = self._bundle_now()  # one bundle for the whole step
        views1 = stack_views([frame], "frame")
        current, ego_estimate = None, None
        previous = state.previous
        if self.reuse and ahead is not None and ahead.bundle_key == key and ahead.frame is frame:
            current = ahead.encoding
            if previous is not None and ahead.ego_previous is previous:
                ego_estimate = ahead.ego_estimate
        if previous is None or previous.depth.shape != frame.depth.shape or frame.scene_start:
            # First frame of this camera (or its image size changed, or its source cut to a new scene):
            # nothing to compare with yet.
            state.extra.clear()
            if current is not None:  # but its own-ref work is the next step's frame 0
                self._remember(state, frame.sequence, key, current)
            self._warm_up(bundle, key, frame)
            world_T_ref = self._world_T_ref(frame)  # an unposed frame is refused now, not only at its pair
            empty = types_pb2.Detections(frame=self.box_frame, bundle_version=version, camera_id=camera,
                                         sequence=frame.sequence, source_timestamp=frame.timestamp,
                                         world_T_frame=codecs.numpy_to_tensor(
                                             self._world_T_frame(frame, world_T_ref)))
            return StepAnswer(detections=empty, egomotion=None)
        views0 = stack_views([previous], "previous")
        dt = moving_interval(views0, views1, modules=bundle.modules, frame_dt=self.frame_dt,
                             pose_fields=("frame.world_T_cam", "frame.world_T_cam"), time_field="frame")
        timings: dict[str, float] = {}
        pair = pair_tensors([views0], [views1], self.runtime.device)
        levels = {"world_T_ref0": self._world_T_ref(previous), "world_T_ref1": self._world_T_ref(frame)}
        with torch.inference_mode():
            out = moving_step(bundle, **pair, **levels, config=self.config,
                              previous=self._cached(state, previous.sequence, key), current=current,
                              ego_estimate=ego_estimate, dt=dt, timings=timings)
        # This frame's own-ref work (its egomotion volume) is the next step's previous-frame cache.
        self._remember(state, frame.sequence, key, out["current"])
        egomotion = None
        if "cam0_T_cam1" in out:
            egomotion = inference_pb2.EgomotionResponse(
                info=inference_pb2.ResponseInfo(bundle_version=version, frame=BOX_FRAME),  # camera to camera
                cam0_T_cam1=codecs.numpy_to_tensor(out["cam0_T_cam1"][0].float().cpu().numpy()))
        (moving,) = detections_results(out, [self.min_score], label="moving")
        # Boxes are in the previous frame's map frame (its camera, or that levelled); sequence/timestamp name
        # the newest frame.
        detections = detections_proto(moving, frame=self.box_frame, bundle_version=version, views=views1,
                                      ref_views=views0, latency_s=time.perf_counter() - started)
        world_T_frame = self._world_T_frame(previous, levels["world_T_ref0"])
        detections.world_T_frame.CopyFrom(codecs.numpy_to_tensor(world_T_frame))
        detections.camera_id = camera
        timings["step_total"] = time.perf_counter() - started
        self._record(timings)
        return StepAnswer(detections=detections, egomotion=egomotion)

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
