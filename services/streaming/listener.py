"""The listener: prints moving-object detections (and egomotion) as they arrive.

Uses a FIFO channel handler pulled from the main thread (natural backpressure, no work on zenoh's
callback thread, clean shutdown — docs/ecosystem.md#zenoh warns against closing sessions under callbacks).
"""

from __future__ import annotations

import json
import threading
import time
from typing import Callable

import numpy as np
import zenoh
from google.protobuf.message import DecodeError

from n3dmap.v1 import types_pb2
from services.inference import codecs
from services.inference.errors import InvalidInput
from services.streaming import keys
from services.streaming.session import ZenohOptions, open_session


def detections_to_json(msg: types_pb2.Detections, *, received_at: float) -> dict:
    return {
        "camera_id": msg.camera_id, "sequence": int(msg.sequence), "frame": msg.frame,
        "bundle_version": msg.bundle_version, "source_timestamp": msg.source_timestamp,
        "end_to_end_ms": round(1000.0 * (received_at - msg.source_timestamp), 2),
        "boxes": [{"x": b.x, "y": b.y, "z": b.z, "lx": b.lx, "ly": b.ly, "lz": b.lz, "yaw": b.yaw,
                   "score": b.score, "label": b.label, "velocity": [b.vx, b.vy, b.vz]} for b in msg.boxes],
        # the pose of the boxes' frame in the cameras' world (4×4 rows), when the bridge knows it
        "world_T_frame": (codecs.tensor_to_numpy(msg.world_T_frame, "world_T_frame").astype(float).tolist()
                          if msg.HasField("world_T_frame") else None),
    }


def format_detections(d: dict) -> str:
    head = (f"[{d['camera_id']} #{d['sequence']}] {len(d['boxes'])} moving object(s) in {d['frame']} "
            f"(e2e {d['end_to_end_ms']:.0f} ms)")
    lines = [head]
    for b in d["boxes"]:
        speed = float(np.linalg.norm(b["velocity"]))
        lines.append(f"    score {b['score']:.2f}  centre ({b['x']:.1f}, {b['y']:.1f}, {b['z']:.1f}) m  "
                     f"size {b['lx']:.1f}×{b['ly']:.1f}×{b['lz']:.1f} m  yaw {b['yaw']:.2f} rad  {speed:.1f} m/s")
    return "\n".join(lines)


def listen(*, zenoh_options: ZenohOptions, camera_id: str = "*", max_messages: int | None = None,
           timeout_s: float | None = None, emit: Callable[[dict], None],
           on_ready: Callable[[str], None] | None = None, stop: threading.Event | None = None) -> int:
    """Receive detections for `camera_id` (a key-expression chunk, `*` = every camera) and call
    `emit` with each as a dict (`on_ready(key)` once subscribed); stop after `max_messages`, after
    `timeout_s` of silence, or when `stop` is set (SIGTERM/SIGINT in the CLI). Returns the count.
    Undecodable samples are reported through `emit` as {"error": ...} rather than ending the loop."""
    session = open_session(zenoh_options)
    count = 0
    try:
        sub = session.declare_subscriber(keys.moving_objects(camera_id), zenoh.handlers.FifoChannel(256))
        if on_ready is not None:
            on_ready(keys.moving_objects(camera_id))
        try:
            last = time.monotonic()
            while (max_messages is None or count < max_messages) and not (stop is not None and stop.is_set()):
                sample = sub.try_recv()
                if sample is None:
                    if timeout_s is not None and time.monotonic() - last > timeout_s:
                        break
                    time.sleep(0.005)
                    continue
                last = time.monotonic()
                msg = types_pb2.Detections()
                try:
                    msg.ParseFromString(sample.payload.to_bytes())
                    detections = detections_to_json(msg, received_at=time.time())
                except (DecodeError, InvalidInput) as e:
                    emit({"error": f"undecodable detections on {sample.key_expr}: {e}"})
                    continue
                emit(detections)
                count += 1
        finally:
            sub.undeclare()
    finally:
        session.close()
    return count


def print_json(d: dict) -> None:
    print(json.dumps(d), flush=True)


def print_human(d: dict) -> None:
    print(d["error"] if "error" in d else format_detections(d), flush=True)
