"""`stream view`'s in-process loop (services.streaming.viewer.view) over a real zenoh session on loopback: a
sink slower than the publisher keeps at most OUTPUT_RING results parked, dropping (and counting) the oldest."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import zenoh

from n3dmap.v1 import inference_pb2
from services.inference import codecs
from services.streaming import keys, viewer
from services.streaming.session import ZenohOptions, open_session


class SlowSink:
    """Blocks in its first egomotion call until released; records every call."""

    def __init__(self) -> None:
        self.release, self.entered, self.egomotion = threading.Event(), threading.Event(), 0

    def log_frame(self, **_):
        pass

    def log_detections(self, **_):
        pass

    def log_egomotion(self, **_):
        self.entered.set()
        self.release.wait(10)
        self.egomotion += 1


def test_a_slow_sink_keeps_a_bounded_backlog_and_counts_what_it_drops(monkeypatch):
    monkeypatch.setattr(viewer, "OUTPUT_RING", 3)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    session = open_session(ZenohOptions(mode="peer", listen=(endpoint,)))
    sink, counts = SlowSink(), {}
    message = inference_pb2.EgomotionResponse(info=inference_pb2.ResponseInfo(bundle_version="t", frame="ref"),
                                              cam0_T_cam1=codecs.numpy_to_tensor(np.eye(4, dtype=np.float32)))
    ready = threading.Event()
    run = threading.Thread(target=lambda: counts.update(result=viewer.view(
        zenoh_options=ZenohOptions(mode="peer", connect=(endpoint,)), camera_id="cam0", sink=sink, timeout_s=2.0,
        wait_for_bridge_s=0, on_ready=lambda key: ready.set())))
    run.start()
    try:
        assert ready.wait(30)
        pub = session.declare_publisher(keys.egomotion("cam0"), congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 30
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)
        pub.put(message.SerializeToString())
        assert sink.entered.wait(10)            # the sink is now stuck in the first message
        for _ in range(9):
            pub.put(message.SerializeToString())
        time.sleep(0.5)                          # delivered and parked (at most 3) while the sink is stuck
        sink.release.set()
        run.join(30)
        pub.undeclare()
    finally:
        sink.release.set()
        session.close()
    result = counts["result"]
    assert result.egomotion == sink.egomotion == 4 and result.outputs_dropped == 6   # 1 + 3 parked; 6 dropped
