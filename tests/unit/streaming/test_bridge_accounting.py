"""The bridge's accounting and fault handling over real zenoh sessions on loopback.

The processor here decodes a tiny JSON payload instead of running models: these tests are about the
bridge's bookkeeping (drops when behind, malformed payloads, duplicates, out-of-order frames,
publisher restarts, status and liveliness), which does not depend on what processing does. The
end-to-end test with the real runtime lives in tests/integration/test_stream_bridge.py.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from types import SimpleNamespace

import pytest
import zenoh

from services.streaming import keys
from services.streaming.bridge import Bridge, MalformedFrame, Outputs
from services.streaming.session import ZenohOptions, open_session


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class JsonProcessor:
    """Decodes {"camera_id", "sequence", "timestamp"[, "fail"]} JSON; optionally slow, to make the bridge fall
    behind. "fail": "refuse" makes `process` refuse the frame as input (MalformedFrame), "crash" fail."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.seen: list[tuple[str, int]] = []
        self.scene_starts: list[int] = []  # the processed frames that came marked as a scene's first
        self.release = threading.Event()
        self.release.set()
        self.entered = threading.Event()  # set when `process` starts (before it waits on `release`)

    def decode(self, payload: bytes):
        try:
            d = json.loads(payload)
            return SimpleNamespace(camera_id=d["camera_id"], sequence=int(d["sequence"]),
                                   timestamp=float(d["timestamp"]), fail=d.get("fail"),
                                   scene_start=bool(d.get("scene_start", False)))
        except (ValueError, KeyError, TypeError) as e:
            raise MalformedFrame(f"not a frame: {e}") from None

    def process(self, camera, state, frame):
        self.entered.set()
        self.release.wait(timeout=10)
        time.sleep(self.delay_s)
        if frame.fail == "refuse":
            raise MalformedFrame("frame.timestamp: not after the previous frame's")
        if frame.fail == "crash":
            raise RuntimeError("a bug in the processor")
        self.seen.append((camera, frame.sequence))
        if frame.scene_start:
            self.scene_starts.append(frame.sequence)
        return Outputs(moving_objects=json.dumps({"seq": frame.sequence}).encode(), egomotion=None)


def frame(camera: str, seq: int, **extra) -> bytes:
    return json.dumps({"camera_id": camera, "sequence": seq, "timestamp": time.time(), **extra}).encode()


def balanced(stats: dict) -> bool:
    """Every received sample is in one bucket (accounting.py)."""
    return stats["received"] == (stats["processed"] + stats["dropped"] + stats["malformed"]
                                 + stats["processing_errors"] + stats["pending"])


def wait_until(predicate, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError("condition not reached in time")


@pytest.fixture
def endpoint():
    return f"tcp/127.0.0.1:{free_port()}"


def test_accounting_identity_malformed_duplicates_restart(endpoint):
    processor = JsonProcessor()
    bridge = Bridge(processor=processor, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t1").start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    results: list[bytes] = []
    sub = client.declare_subscriber(keys.moving_objects("cam0"), lambda s: results.append(s.payload.to_bytes()))
    try:
        time.sleep(0.5)  # let the peers connect and the subscription propagate
        pub = client.declare_publisher(keys.rgbd("cam0"), congestion_control=zenoh.CongestionControl.BLOCK)

        def put(payload: bytes, publisher: str) -> None:
            pub.put(payload, attachment=f"pub={publisher}".encode())
            time.sleep(0.05)  # one at a time: this test is about classification, not drops

        put(frame("cam0", 0), "A")
        put(frame("cam0", 1), "A")
        put(b"\x00garbage", "A")                      # malformed
        put(frame("cam0", 1), "A")                    # duplicate
        put(frame("cam0", 0), "A")                    # out of order
        put(frame("other", 2), "A")                   # names another camera: malformed
        put(frame("cam0", 0), "B")                    # publisher restarted: accepted again
        put(frame("cam0", 1), "B")
        wait_until(lambda: bridge.status()["cameras"].get("cam0", {}).get("received") == 8
                   and bridge.status()["cameras"]["cam0"]["pending"] == 0)
        wait_until(lambda: len(results) == 4)
        stats = bridge.status()["cameras"]["cam0"]
        assert stats["processed"] == 4 and processor.seen == [("cam0", 0), ("cam0", 1), ("cam0", 0), ("cam0", 1)]
        assert stats["malformed"] == 2
        assert stats["dropped_duplicate"] == 1 and stats["dropped_out_of_order"] == 1
        assert stats["publisher_restarts"] == 1
        assert balanced(stats) and stats["pending"] == stats["processing_errors"] == 0
        assert stats["latency_ms"]["count"] == 4 and stats["latency_ms"]["p50"] >= 0

        # Status answers over zenoh as JSON; the liveliness token announces the bridge.
        replies = list(client.get(keys.bridge_status("t1"), timeout=5.0))
        assert json.loads(replies[0].ok.payload.to_bytes())["cameras"]["cam0"]["processed"] == 4
        tokens = [str(r.ok.key_expr) for r in client.liveliness().get(keys.bridge_token("*"), timeout=5.0)]
        assert keys.bridge_token("t1") in tokens
        pub.undeclare()
    finally:
        sub.undeclare()
        client.close()
        bridge.stop()


def test_behind_bridge_processes_newest_and_counts_drops(endpoint):
    processor = JsonProcessor(delay_s=0.05)
    processor.release.clear()  # hold the worker so frames pile up behind it
    bridge = Bridge(processor=processor, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t2").start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        time.sleep(0.5)
        pub = client.declare_publisher(keys.rgbd("cam1"), congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(frame("cam1", 0), attachment=b"pub=A")
        assert processor.entered.wait(10)  # the worker has taken frame 0 and waits on `release`
        for seq in range(1, 30):
            pub.put(frame("cam1", seq), attachment=b"pub=A")
        wait_until(lambda: bridge.status()["cameras"]["cam1"]["received"] == 30)
        mid = bridge.status()["cameras"]["cam1"]
        assert mid["pending"] == 2  # frame 0 in the worker, frame 29 parked; 1..28 replaced
        assert balanced(mid)
        processor.release.set()
        wait_until(lambda: bridge.status()["cameras"]["cam1"]["pending"] == 0)
        stats = bridge.status()["cameras"]["cam1"]
        assert balanced(stats)
        assert stats["dropped_behind"] >= 20           # it skipped what it could not keep up with
        assert processor.seen[-1] == ("cam1", 29)      # ...and processed the newest frame
        assert processor.scene_starts == [] and stats["scene_starts"] == 0  # no cut among the dropped
        pub.undeclare()
    finally:
        client.close()
        bridge.stop()


class FlagProcessor(JsonProcessor):
    """JsonProcessor that reads a payload's scene_start flag without decoding it (RuntimeProcessor's way)."""

    def __init__(self) -> None:
        super().__init__()
        self.flag_reads = 0

    def starts_scene(self, payload: bytes) -> bool:
        self.flag_reads += 1
        return b'"scene_start": true' in payload


@pytest.mark.parametrize("processor_type", [JsonProcessor, FlagProcessor])
def test_a_dropped_scene_start_marks_the_frame_that_replaced_it(endpoint, processor_type):
    """With a scene's first frame dropped behind, the newest frame (the one processed instead) is answered
    as a scene's first, so no pair spans the cut; a frame replaced after it passes the mark on too, a drop
    without a cut marks nothing, and a marked frame the processor refuses passes the mark to the next one."""
    processor = processor_type()
    processor.release.clear()
    bridge = Bridge(processor=processor, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t6").start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        time.sleep(0.5)
        pub = client.declare_publisher(keys.rgbd("cam5"), congestion_control=zenoh.CongestionControl.BLOCK)

        def held(sequences, extra=None):
            """Frames `sequences` sent while the worker holds the first; `extra`: {sequence: payload fields}."""
            first, *rest = sequences
            processor.entered.clear()
            pub.put(frame("cam5", first), attachment=b"pub=A")
            assert processor.entered.wait(10)  # the worker has taken `first` and waits on `release`
            for seq in rest:
                pub.put(frame("cam5", seq, **(extra or {}).get(seq, {})), attachment=b"pub=A")
            wait_until(lambda: bridge.status()["cameras"]["cam5"]["received"] == sequences[-1] + 1)
            processor.release.set()
            wait_until(lambda: bridge.status()["cameras"]["cam5"]["pending"] == 0)
            processor.release.clear()

        cut = {"scene_start": True}
        held([0, 1, 2, 3], {1: cut})       # the cut's frame 1 and frame 2 dropped: 3 starts the scene
        held([4, 5, 6, 7])                 # dropped frames without a cut: nothing marked
        held([8, 9, 10], {9: cut, 10: {"fail": "refuse"}})  # 9 dropped, 10 carries its mark and is refused
        processor.release.set()
        pub.put(frame("cam5", 11), attachment=b"pub=A")     # ... so 11 starts the scene
        wait_until(lambda: bridge.status()["cameras"]["cam5"]["processed"] == 6
                   and bridge.status()["cameras"]["cam5"]["pending"] == 0)
        stats = bridge.status()["cameras"]["cam5"]
        assert [s for _, s in processor.seen] == [0, 3, 4, 7, 8, 11] and processor.scene_starts == [3, 11]
        assert stats["scene_starts"] == 2 and stats["dropped_behind"] == 5 and stats["malformed"] == 1
        assert balanced(stats)
        if processor_type is FlagProcessor:
            assert processor.flag_reads == 4  # frames 1, 5, 6, 9 read without a decode; 2 and 10 carried a mark
        pub.undeclare()
    finally:
        processor.release.set()
        client.close()
        bridge.stop()


def test_refused_and_failed_frames_are_counted_apart(endpoint):
    """A frame the processor refuses as input is malformed; one whose processing fails otherwise is a
    processing error, not the sender's mistake. Neither advances the camera: the next frame compares with
    the last one processed."""
    processor = JsonProcessor()
    bridge = Bridge(processor=processor, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t3").start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        time.sleep(0.5)
        pub = client.declare_publisher(keys.rgbd("cam2"), congestion_control=zenoh.CongestionControl.BLOCK)
        for payload in (frame("cam2", 0), frame("cam2", 1, fail="refuse"), frame("cam2", 2, fail="crash"),
                        frame("cam2", 3)):
            pub.put(payload, attachment=b"pub=A")
            time.sleep(0.05)
        wait_until(lambda: bridge.status()["cameras"].get("cam2", {}).get("received") == 4
                   and bridge.status()["cameras"]["cam2"]["pending"] == 0)
        stats = bridge.status()["cameras"]["cam2"]
        assert stats["processed"] == 2 and stats["malformed"] == 1 and stats["processing_errors"] == 1
        assert balanced(stats) and processor.seen == [("cam2", 0), ("cam2", 3)]
        pub.undeclare()
    finally:
        client.close()
        bridge.stop()


class AheadProcessor(JsonProcessor):
    """JsonProcessor with an `encode_ahead` that records which thread ran it and which frame it was handed
    as the previous one; `process` checks it received the look-ahead made for its own frame."""

    def __init__(self, delay_s: float = 0.0) -> None:
        super().__init__(delay_s)
        self.ahead_calls: list[tuple[int, int | None, str]] = []
        self.used: list[int] = []

    def encode_ahead(self, frame, previous):
        before = None if previous is None else previous["sequence"]
        self.ahead_calls.append((frame.sequence, before, threading.current_thread().name))
        if frame.fail == "ahead-crash":
            raise RuntimeError("a bug in the look-ahead")
        return {"sequence": frame.sequence}

    def process(self, camera, state, frame, ahead=None):
        if ahead is not None:
            assert ahead["sequence"] == frame.sequence
            self.used.append(frame.sequence)
        return super().process(camera, state, frame)


def test_look_ahead_runs_beside_the_worker_and_keeps_the_accounting(endpoint):
    """Frames are encoded ahead on the look-ahead thread, each handed the look-ahead of the frame the worker
    took last; the worker processes only finished look-aheads; a failing look-ahead costs nothing but the
    worker redoing the work; drops and the accounting identity are as without look-ahead. With
    lookahead=False no look-ahead runs."""
    processor = AheadProcessor(delay_s=0.05)
    bridge = Bridge(processor=processor, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t4").start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        time.sleep(0.5)
        pub = client.declare_publisher(keys.rgbd("cam3"), congestion_control=zenoh.CongestionControl.BLOCK)
        for seq in range(4):
            pub.put(frame("cam3", seq, **({"fail": "ahead-crash"} if seq == 2 else {})), attachment=b"pub=A")
            time.sleep(0.15)  # one at a time
        wait_until(lambda: bridge.status()["cameras"].get("cam3", {}).get("processed") == 4)
        assert [s for _, s in processor.seen] == [0, 1, 2, 3]
        assert processor.used == [0, 1, 3]  # frame 2's look-ahead failed: processed without one
        assert [(s, b) for s, b, _ in processor.ahead_calls] == [(0, None), (1, 0), (2, 1), (3, None)]
        assert {name for *_, name in processor.ahead_calls} == {"n3dmap-bridge-lookahead"}
        for seq in range(4, 30):  # faster than the 50 ms processing: the bridge falls behind and drops
            pub.put(frame("cam3", seq), attachment=b"pub=A")
        wait_until(lambda: bridge.status()["cameras"]["cam3"]["received"] == 30
                   and bridge.status()["cameras"]["cam3"]["pending"] == 0)
        stats = bridge.status()["cameras"]["cam3"]
        assert balanced(stats) and stats["dropped_behind"] > 0 and processor.seen[-1] == ("cam3", 29)
        pub.undeclare()
    finally:
        client.close()
        bridge.stop()
    plain = AheadProcessor()
    bridge = Bridge(processor=plain, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t5",
                    lookahead=False).start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        time.sleep(0.5)
        client.put(keys.rgbd("cam4"), frame("cam4", 0), attachment=b"pub=A")
        wait_until(lambda: bridge.status()["cameras"].get("cam4", {}).get("processed") == 1)
        assert plain.ahead_calls == [] and plain.used == [] and plain.seen == [("cam4", 0)]
    finally:
        client.close()
        bridge.stop()


def test_idle_cameras_are_forgotten_and_a_flood_of_cameras_is_capped(endpoint):
    now = [1000.0]
    processor = JsonProcessor()
    bridge = Bridge(processor=processor, zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="t7",
                    clock=lambda: now[0], idle_evict_s=60.0, max_cameras=2).start()
    client = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        time.sleep(0.5)
        for camera, seq in (("a", 0), ("a", 1), ("b", 5)):
            client.put(keys.rgbd(camera), frame(camera, seq))
            time.sleep(0.05)
        wait_until(lambda: processor.seen == [("a", 0), ("a", 1), ("b", 5)])
        client.put(keys.rgbd("c"), frame("c", 0))            # a third camera while two are tracked: refused, counted
        wait_until(lambda: bridge.status()["cameras"].get("_too_many_cameras", {}).get("received") == 1)
        assert bridge.status()["cameras"]["_too_many_cameras"]["dropped"] == 1 and "c" not in bridge.status()["cameras"]
        assert set(bridge._states) == {"a", "b"}
        assert ("pub", keys.moving_objects("a")) in bridge._publishers
        now[0] += 61.0                                       # both silent past the limit: forgotten
        wait_until(lambda: not bridge._states and "a" not in bridge.status()["cameras"])
        assert not bridge._publishers                        # their publishers undeclared with them
        retired = bridge.status()["cameras"]["_retired"]
        assert retired["received"] == 3 and retired["processed"] == 3 and balanced(retired)
        # camera a comes back restarted at sequence 0: a fresh camera again (it was dropped as out of order
        # while its old state lived), and c now has room
        client.put(keys.rgbd("a"), frame("a", 0))
        time.sleep(0.05)
        client.put(keys.rgbd("c"), frame("c", 0))
        wait_until(lambda: processor.seen[3:] == [("a", 0), ("c", 0)])
        stats = bridge.status()["cameras"]
        assert stats["a"]["processed"] == 1 and stats["a"]["dropped"] == 0 and stats["c"]["processed"] == 1
    finally:
        client.close()
        bridge.stop()


def test_idle_eviction_runs_on_a_monotonic_clock_by_default(endpoint):
    # a wall-clock step (NTP, a resumed host) past idle_evict_s would otherwise evict every live camera
    assert Bridge(processor=JsonProcessor(), zenoh_options=ZenohOptions(listen=(endpoint,))).clock is time.monotonic


def test_a_start_that_fails_part_way_stops_what_it_started(endpoint):
    bridge = Bridge(processor=JsonProcessor(), zenoh_options=ZenohOptions(listen=(endpoint,)), bridge_id="bad?id")
    with pytest.raises(zenoh.ZError):       # the status key of this id is no key expression
        bridge.start()
    assert bridge._session is None and not bridge._declared
    assert bridge._worker is not None and not bridge._worker.is_alive()
    assert bridge._lookahead is None or not bridge._lookahead.is_alive()
