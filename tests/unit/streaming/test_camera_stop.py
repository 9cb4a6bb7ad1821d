"""services.streaming.camera.publish_frames: a stop event ends a slow camera within moments, mid-period."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from services.streaming.camera import publish_frames
from services.streaming.session import ZenohOptions


def _frame() -> dict:
    K = np.array([[8, 0, 4, 0], [0, 8, 4, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)
    return {"rgb": np.zeros((8, 8, 3), np.uint8), "depth": np.ones((8, 8), np.float32), "pix_T_cam": K,
            "world_T_cam": np.eye(4, dtype=np.float32)}


def test_a_stop_ends_a_slow_camera_mid_period():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    stop = threading.Event()
    sent_at = []

    def on_sent(i):
        sent_at.append(time.monotonic())
        threading.Timer(0.2, stop.set).start()   # a SIGTERM 0.2 s into the 100 s wait for the next frame

    sent = publish_frames((_frame() for _ in range(3)), camera_id="cam0", rate_hz=0.01, max_frames=None,
                          zenoh_options=ZenohOptions(mode="peer", listen=(endpoint,)), wait_for_bridge_s=0,
                          on_sent=on_sent, stop=stop)
    assert sent == 1 and time.monotonic() - sent_at[0] < 5.0   # not the period's 100 s
