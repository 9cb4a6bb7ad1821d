"""The simulated camera: publishes RGB-D frames as `n3dmap.v1.Frame` on `n3dmap/<camera>/rgbd`.

Each sample carries the attachment `pub=<publisher id>` (a fresh id per process), which lets the
bridge tell a restarted camera (sequence back at 0) from out-of-order frames. Frames are paced at
`rate_hz` against a monotonic clock (no drift from processing time; after a stall of the source,
such as rendering the next synthetic episode, the schedule restarts instead of bursting); `CongestionControl.BLOCK`
means zenoh never silently drops a frame on the way out (docs/ecosystem.md#zenoh).
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from typing import Iterable, Iterator

import numpy as np
import zenoh

from core.errors import ConfigError
from n3dmap.v1 import types_pb2
from services.inference.codecs import encode_png_depth, encode_png_rgb, numpy_to_tensor
from services.streaming import keys
from services.streaming.session import ZenohOptions, open_session

log = logging.getLogger("n3dmap.camera")


def encode_frame(frame: dict, *, camera_id: str, sequence: int, timestamp: float, capture_time: float = 0.0,
                 encoding: str = "raw") -> bytes:
    """A source frame dict (rgb H×W×3 uint8, depth H×W float32 m, pix_T_cam 4×4, world_T_cam 4×4, optional
    scene_start: the source cut to a new scene here) → serialized `Frame`. `capture_time`: seconds on the
    capture clock (0: not given). `encoding`: "raw" (little-endian arrays, cheapest on one host) or "png"
    (RGB PNG + uint16-millimetre depth PNG, smaller on a network)."""
    msg = types_pb2.Frame(camera_id=camera_id, sequence=sequence, timestamp=timestamp, capture_time=capture_time,
                          scene_start=bool(frame.get("scene_start", False)))
    if encoding == "png":
        msg.rgb.png = encode_png_rgb(frame["rgb"])
        msg.depth.png = encode_png_depth(frame["depth"])
    elif encoding == "raw":
        msg.rgb.array.CopyFrom(numpy_to_tensor(np.ascontiguousarray(frame["rgb"], np.uint8)))
        msg.depth.array.CopyFrom(numpy_to_tensor(np.ascontiguousarray(frame["depth"], np.float32)))
    else:
        raise ValueError(f"encoding must be 'raw' or 'png', got {encoding!r}")
    msg.pix_T_cam.CopyFrom(numpy_to_tensor(np.asarray(frame["pix_T_cam"], np.float32)))
    msg.world_T_cam.CopyFrom(numpy_to_tensor(np.asarray(frame["world_T_cam"], np.float32)))
    return msg.SerializeToString()


def publish_frames(frames: Iterable[dict], *, camera_id: str, zenoh_options: ZenohOptions, rate_hz: float,
                   max_frames: int | None, encoding: str = "raw", wait_for_bridge_s: float = 10.0,
                   on_sent=None, stop: threading.Event | None = None) -> int:
    """Publish frames at `rate_hz` until the source ends or `max_frames` were sent; returns the count.

    Each frame's `timestamp` is when it is sent; a source that knows when its frames were captured (a
    frame's `capture_offset`, sources.py) also gets `capture_time`: the first frame's send time plus its
    offset, so a recording replayed at another rate keeps its own clock for motion.

    Before the first frame it waits up to `wait_for_bridge_s` for a bridge's liveliness token, so
    a camera started together with its bridge does not publish into the void. `stop` (set by a signal
    handler) ends it within moments even while it waits out a long period (a slow --rate)."""
    if rate_hz <= 0:
        raise ConfigError(f"--rate must be positive, got {rate_hz}")
    stop = stop or threading.Event()
    session = open_session(zenoh_options)
    publisher_id = uuid.uuid4().hex[:12]
    attachment = f"pub={publisher_id}".encode()
    sent = 0
    try:
        _wait_for_bridge(session, wait_for_bridge_s)
        pub = session.declare_publisher(keys.rgbd(camera_id), congestion_control=zenoh.CongestionControl.BLOCK)
        period = 1.0 / rate_hz
        next_at = time.monotonic()
        capture_zero = None                  # wall time of capture offset 0
        iterator: Iterator[dict] = iter(frames)
        while max_frames is None or sent < max_frames:
            try:
                frame = next(iterator)
            except StopIteration:
                break
            delay = next_at - time.monotonic()
            if delay > 0:
                if stop.wait(delay):   # time.sleep would sit out the whole period after a SIGTERM
                    break
            elif delay < -period:
                # The source stalled (a synthetic episode being rendered): resume at the rate from
                # now instead of bursting out the frames "missed" meanwhile, as a real camera would.
                next_at = time.monotonic()
            now = time.time()
            offset = frame.get("capture_offset")
            if offset is not None and capture_zero is None:
                capture_zero = now - offset
            payload = encode_frame(frame, camera_id=camera_id, sequence=sent, timestamp=now,
                                   capture_time=0.0 if offset is None else capture_zero + offset, encoding=encoding)
            pub.put(payload, attachment=attachment)
            if on_sent is not None:
                on_sent(sent)
            sent += 1
            next_at += period
        # Give the last samples time to leave before the session closes.
        time.sleep(0.2)
        pub.undeclare()
    finally:
        session.close()
    return sent


def _wait_for_bridge(session: zenoh.Session, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        replies = list(session.liveliness().get(keys.bridge_token("*"), timeout=1.0))
        if any(r.ok is not None for r in replies):
            return True
        time.sleep(0.2)
    if timeout_s > 0:
        log.warning("no bridge answered within %.1f s; publishing anyway", timeout_s)
    return False
