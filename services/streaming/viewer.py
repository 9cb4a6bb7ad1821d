"""The stream viewer: subscribes to one camera's frames and the bridge's outputs over zenoh and hands
them, decoded, to a sink (services.viz.rerun_stream.StreamRecorder in `n3dmap stream view`).

One subscriber on `n3dmap/<camera>/*` (frames `rgbd`, detections `moving_objects`, `egomotion`) whose
callback only parks the payload (docs/ecosystem.md#zenoh: no work on zenoh's thread): detections and egomotion in
one unbounded FIFO, so every processed frame's entry reaches the sink and an egomotion message follows
the detections it belongs to (the bridge publishes them in that order, and it carries no sequence of
its own); frames in a small ring that drops the oldest when the sink falls behind, so a slow viewer never
pushes back on the camera. The main thread decodes and logs.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np
import zenoh
from google.protobuf.message import DecodeError

from n3dmap.v1 import inference_pb2, types_pb2
from services.inference import codecs
from services.inference.errors import InvalidInput
from services.streaming import keys
from services.streaming.session import ZenohOptions, open_session

FRAME_RING = 32  # frames parked at most; older ones are dropped (and counted) when the sink lags
# Detections / egomotion messages parked at most. They are what the counts promise and are served first, so
# the queue only grows when the publisher outpaces the sink for long: then the oldest go (and are counted),
# rather than memory growing with the backlog.
OUTPUT_RING = 4096
EGOMOTION_GRACE_S = 0.5  # after the last wanted Detections, how long its egomotion may take to arrive


class StreamSink(Protocol):
    def log_frame(self, *, sequence: int, timestamp: float, rgb: np.ndarray, depth: np.ndarray,
                  pix_T_cam: np.ndarray, world_T_cam: np.ndarray | None) -> None: ...

    def log_detections(self, *, sequence: int, timestamp: float, boxes: np.ndarray, scores: np.ndarray,
                       velocities: np.ndarray, world_T_frame: np.ndarray | None, received_at: float) -> None: ...

    def log_egomotion(self, *, cam0_T_cam1: np.ndarray) -> None: ...


@dataclass
class ViewCounts:
    frames: int = 0
    frames_dropped: int = 0
    outputs_dropped: int = 0
    detections: int = 0
    egomotion: int = 0
    undecodable: int = 0


def decode_frame(payload: bytes) -> dict:
    """`Frame` bytes -> rgb H×W×3 uint8, depth H×W float32 m, pix_T_cam 4×4, world_T_cam 4×4 | None,
    sequence, timestamp."""
    msg = types_pb2.Frame()
    msg.ParseFromString(payload)
    images = {}
    for name, image in (("rgb", msg.rgb), ("depth", msg.depth)):
        which = image.WhichOneof("encoding")
        if which == "png":
            images[name] = (codecs.decode_png_depth if name == "depth" else codecs.decode_png_rgb)(image.png, name)
        elif which == "array":
            images[name] = codecs.tensor_to_numpy(image.array, name)
        else:
            raise InvalidInput(name, "missing")
    return {"rgb": np.asarray(images["rgb"], np.uint8), "depth": np.asarray(images["depth"], np.float32),
            "pix_T_cam": codecs.tensor_to_numpy(msg.pix_T_cam, "pix_T_cam"),
            "world_T_cam": codecs.tensor_to_numpy(msg.world_T_cam, "world_T_cam") if msg.HasField("world_T_cam") else None,
            "sequence": int(msg.sequence), "timestamp": float(msg.timestamp)}


def decode_detections(payload: bytes) -> dict:
    """`Detections` bytes -> boxes N×7, scores N, velocities N×3, world_T_frame 4×4 | None, sequence, timestamp."""
    msg = types_pb2.Detections()
    msg.ParseFromString(payload)
    boxes = np.array([[b.x, b.y, b.z, b.lx, b.ly, b.lz, b.yaw] for b in msg.boxes], np.float32).reshape(-1, 7)
    return {"boxes": boxes, "scores": np.array([b.score for b in msg.boxes], np.float32),
            "velocities": np.array([[b.vx, b.vy, b.vz] for b in msg.boxes], np.float32).reshape(-1, 3),
            "world_T_frame": (codecs.tensor_to_numpy(msg.world_T_frame, "world_T_frame")
                              if msg.HasField("world_T_frame") else None),
            "sequence": int(msg.sequence), "timestamp": float(msg.source_timestamp)}


def decode_egomotion(payload: bytes) -> np.ndarray:
    """`EgomotionResponse` bytes -> cam0_T_cam1 4×4."""
    msg = inference_pb2.EgomotionResponse()
    msg.ParseFromString(payload)
    return codecs.tensor_to_numpy(msg.cam0_T_cam1, "cam0_T_cam1").reshape(4, 4)


def view(*, zenoh_options: ZenohOptions, camera_id: str, sink: StreamSink, stop: threading.Event | None = None,
         max_detections: int | None = None, timeout_s: float | None = None, duration_s: float | None = None,
         on_ready: Callable[[str], None] | None = None, warn: Callable[[str], None] | None = None,
         wait_for_bridge_s: float = 10.0) -> ViewCounts:
    """Feed `sink` with `camera_id`'s stream until `max_detections` Detections were logged, `timeout_s`
    of silence, `duration_s`, or `stop` is set. Returns the counts. Undecodable payloads are counted
    (and reported through `warn`), never fatal. `on_ready(key)` is called once the session is connected,
    subscribed, and has seen a bridge's liveliness token (or waited `wait_for_bridge_s` for one)."""
    counts = ViewCounts()
    frames: collections.deque = collections.deque()
    outputs: collections.deque = collections.deque()
    cond = threading.Condition()
    key = f"{keys.PREFIX}/{camera_id}/*"

    def on_sample(sample: zenoh.Sample) -> None:  # zenoh's thread: park and return
        stream = str(sample.key_expr).rsplit("/", 1)[-1]
        item = (stream, sample.payload.to_bytes(), time.time())
        with cond:
            if stream == "rgbd":
                if len(frames) >= FRAME_RING:
                    frames.popleft()
                    counts.frames_dropped += 1
                frames.append(item)
            elif stream in ("moving_objects", "egomotion"):
                if len(outputs) >= OUTPUT_RING:
                    outputs.popleft()
                    counts.outputs_dropped += 1
                outputs.append(item)
            cond.notify()

    session = open_session(zenoh_options)
    try:
        limits = [s for s in (duration_s, timeout_s) if s is not None]
        give_up_at = time.monotonic() + min(limits) if limits else None
        if not _wait_connected(session, stop, warn, give_up_at=give_up_at):
            return counts
        # Declared on an established link, then confirmed by seeing a bridge (as the camera does):
        # once a bridge's token is visible here, this subscription is known to it too.
        sub = session.declare_subscriber(key, on_sample)
        if wait_for_bridge_s > 0 and not _wait_for_bridge(session, wait_for_bridge_s) and warn is not None:
            warn(f"no bridge answered within {wait_for_bridge_s:.0f} s; showing whatever arrives")
        if on_ready is not None:
            on_ready(key)
        started = last = time.monotonic()
        done_at = None  # when the max_detections-th Detections was logged
        try:
            while not (stop is not None and stop.is_set()):
                if max_detections is not None and counts.detections >= max_detections:
                    # The egomotion of that last pair follows it: wait a moment for it, then stop.
                    done_at = done_at or time.monotonic()
                    with cond:
                        follows = bool(outputs) and outputs[0][0] == "egomotion"
                    if not follows and (outputs or time.monotonic() - done_at > EGOMOTION_GRACE_S):
                        break
                now = time.monotonic()
                if duration_s is not None and now - started >= duration_s:
                    break
                if timeout_s is not None and now - last > timeout_s:
                    break
                with cond:
                    if not frames and not outputs:
                        cond.wait(0.1)
                    # Outputs first: they are what the counts promise; a frame can wait a moment.
                    item = outputs.popleft() if outputs else frames.popleft() if frames else None
                if item is None:
                    continue
                last = time.monotonic()
                _dispatch(item, sink, counts, warn)
        finally:
            sub.undeclare()
        if done_at is None:
            # Stopped (signal, silence, duration): what already arrived is logged too — on a loaded
            # machine the last detections may still be queued when the caller stops the view.
            with cond:
                remaining = [*outputs, *frames]
                outputs.clear()
                frames.clear()
            for item in remaining:
                _dispatch(item, sink, counts, warn)
    finally:
        session.close()
    return counts


def _wait_connected(session: zenoh.Session, stop: threading.Event | None, warn, *, give_up_at: float | None,
                    warn_after_s: float = 5.0) -> bool:
    """Until the session is connected to another zenoh node (False if `stop` is set or `give_up_at`
    passes first).

    A peer whose endpoint is not up yet (a bridge still loading its model) retries the connection in
    the background, and only once connected does its subscription reach the publishers: announcing
    readiness before that would let a caller start the camera into a viewer that misses its first frames."""
    started, warned = time.monotonic(), False
    while not (list(session.info.peers_zid()) or list(session.info.routers_zid())):
        if (stop is not None and stop.wait(0.05)) or (give_up_at is not None and time.monotonic() > give_up_at):
            return False
        if stop is None:
            time.sleep(0.05)
        if not warned and warn is not None and time.monotonic() - started > warn_after_s:
            warn(f"no zenoh peer or router reachable after {warn_after_s:.0f} s; still trying")
            warned = True
    return True


def _wait_for_bridge(session: zenoh.Session, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while True:
        replies = list(session.liveliness().get(keys.bridge_token("*"), timeout=1.0))
        if any(r.ok is not None for r in replies):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)


def _dispatch(item, sink: StreamSink, counts: ViewCounts, warn) -> None:
    stream, payload, received_at = item
    try:
        if stream == "rgbd":
            sink.log_frame(**{k: v for k, v in decode_frame(payload).items()})
            counts.frames += 1
        elif stream == "moving_objects":
            sink.log_detections(**decode_detections(payload), received_at=received_at)
            counts.detections += 1
        else:
            sink.log_egomotion(cam0_T_cam1=decode_egomotion(payload))
            counts.egomotion += 1
    except (DecodeError, InvalidInput, ValueError) as e:
        counts.undecodable += 1
        if warn is not None:
            warn(f"undecodable {stream} payload: {' '.join(str(e).split())}")
