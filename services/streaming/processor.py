"""The bridge's frame processor: zenoh payloads in and out of the shared stream step.

Decoding and validation are the gRPC transport's own (`services.inference.wire.view_from_proto`), so a
frame is accepted on zenoh exactly when it would be accepted by the Frame RPCs; the model work is
`services.inference.camera_stream.MovingStream`, the same step gRPC StreamMovingObjects runs. Its
Detections go to `n3dmap/<camera>/moving_objects` and its egomotion to `n3dmap/<camera>/egomotion`. A
pair the step refuses (a clock that does not advance, missing poses a bundle without egomotion needs)
is a malformed frame.
"""

from __future__ import annotations

from google.protobuf.message import DecodeError

from core.pipeline.moving_boxes import DEFAULT_DT, MovingObjectsConfig
from n3dmap.v1 import types_pb2
from services.inference.camera_state import CameraState
from services.inference.camera_stream import MovingStream
from services.inference.errors import InvalidInput
from services.inference.runtime import Runtime
from services.inference.validation import View
from services.inference.wire import view_from_proto
from services.streaming.bridge import MalformedFrame, Outputs


def _parse(payload: bytes) -> types_pb2.Frame:
    """The payload as an n3dmap.v1.Frame message (not yet validated); MalformedFrame if it does not parse."""
    msg = types_pb2.Frame()
    try:
        msg.ParseFromString(payload)
    except DecodeError as e:
        raise MalformedFrame(f"payload is not an n3dmap.v1.Frame: {e}") from None
    return msg


class RuntimeProcessor(MovingStream):
    """Decode `Frame` payloads and run egomotion + moving objects on the runtime's bundle."""

    def __init__(self, runtime: Runtime, *, min_score: float = 0.0, reuse: bool = True,
                 frame_dt: float = DEFAULT_DT, objects: MovingObjectsConfig | None = None, level: bool = False,
                 level_ahead: float = 0.0, ground_y: float | None = None) -> None:
        """As MovingStream; refuses a bundle that cannot find moving objects."""
        if "moving_objects" not in runtime.routes:
            raise ValueError(f"--bundle {runtime.config.bundle_dir} (version {runtime.version}) cannot serve the "
                             f"stream bridge: it lacks the modules for moving_objects (loaded modules: {', '.join(runtime.modules)}); "
                             "train the flow module into the bundle first")
        super().__init__(runtime, min_score=min_score, frame_dt=frame_dt, objects=objects, reuse=reuse,
                         level=level, level_ahead=level_ahead, ground_y=ground_y)

    def decode(self, payload: bytes) -> View:
        try:
            return view_from_proto(_parse(payload), "frame")
        except InvalidInput as e:
            raise MalformedFrame(str(e)) from None

    @staticmethod
    def starts_scene(payload: bytes) -> bool:
        """The payload's Frame.scene_start, read without validating the frame (the bridge asks it of a
        frame it replaces unprocessed); False for a payload that does not parse."""
        try:
            return bool(_parse(payload).scene_start)
        except MalformedFrame:
            return False

    def process(self, camera: str, state: CameraState, frame: View, ahead=None) -> Outputs:
        try:
            answer = self.step(camera, state, frame, ahead)
        except InvalidInput as e:
            raise MalformedFrame(str(e)) from None
        return Outputs(moving_objects=answer.detections.SerializeToString(),
                       egomotion=None if answer.egomotion is None else answer.egomotion.SerializeToString())
