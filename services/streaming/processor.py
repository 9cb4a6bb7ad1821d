"""The bridge's frame processor over the shared inference runtime.

Decoding and validation are the gRPC transport's own (`services.inference.wire.view_from_proto`),
so a frame is accepted on zenoh exactly when it would be accepted by the Frame RPCs. Each frame
after a camera's first runs, on the bridge's worker thread, egomotion (previous → current; the
camera-to-camera motion is published on `n3dmap/<camera>/egomotion`) and the moving-object route
(egomotion-stabilised 3D flow → moving objects), whose boxes are published in the frame `ref` =
the camera at the previous frame, with `world_T_frame` naming that pose.
"""

from __future__ import annotations

import time

from google.protobuf.message import DecodeError

from n3dmap.v1 import inference_pb2, types_pb2
from services.inference import codecs
from services.inference.errors import InvalidInput
from services.inference.routes import BOX_FRAME, MovingInput, PairInput
from services.inference.runtime import Runtime
from services.inference.validation import View, stack_views
from services.inference.wire import detections_proto, view_from_proto
from services.streaming.bridge import CameraState, MalformedFrame, Outputs


class RuntimeProcessor:
    """Decode `Frame` payloads and run egomotion + moving objects through a `Runtime`."""

    def __init__(self, runtime: Runtime, *, min_score: float = 0.0) -> None:
        missing = [r for r in ("moving_objects",) if r not in runtime.routes]
        if missing:
            raise ValueError(f"bundle {runtime.version} cannot serve the stream bridge: it lacks the modules for "
                             f"{', '.join(missing)} (loaded modules: {', '.join(runtime.modules)}); "
                             "train the flow module into the bundle first")
        self.runtime = runtime
        self.min_score = min_score

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

    def process(self, camera: str, state: CameraState, frame: View) -> Outputs:
        started = time.time()
        views1 = stack_views([frame], "frame")
        if state.previous is None or state.previous.depth.shape != frame.depth.shape:
            # First frame of this camera (or its image size changed): nothing to compare with yet.
            empty = types_pb2.Detections(frame=BOX_FRAME, bundle_version=self.runtime.version, camera_id=camera,
                                         sequence=frame.sequence, source_timestamp=frame.timestamp,
                                         world_T_frame=codecs.numpy_to_tensor(frame.world_T_cam))
            return Outputs(moving_objects=empty.SerializeToString(), egomotion=None)
        views0 = stack_views([state.previous], "previous")
        egomotion = None
        if "egomotion" in self.runtime.routes:
            (ego,) = self.runtime.infer_sync("egomotion", [PairInput(views0=views0, views1=views1)])
            egomotion = inference_pb2.EgomotionResponse(
                info=inference_pb2.ResponseInfo(bundle_version=self.runtime.version, frame=BOX_FRAME),
                cam0_T_cam1=codecs.numpy_to_tensor(ego.cam0_T_cam1)).SerializeToString()
        (moving,) = self.runtime.infer_sync(
            "moving_objects", [MovingInput(views0=views0, views1=views1, min_score=self.min_score)])
        # Boxes are in ref = the camera at the previous frame; sequence/timestamp name the newest frame.
        detections = detections_proto(moving, frame=BOX_FRAME, bundle_version=self.runtime.version, views=views0,
                                      latency_s=time.time() - started)
        detections.sequence = frame.sequence
        detections.source_timestamp = frame.timestamp
        detections.camera_id = camera
        return Outputs(moving_objects=detections.SerializeToString(), egomotion=egomotion)
