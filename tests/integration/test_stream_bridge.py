"""The zenoh stream bridge end to end: `n3dmap stream bridge|camera|listen` as separate processes.

Every process is a real `python -m services.cli.main stream ...` with its own zenoh session in peer
mode on a free loopback port (the bridge listens, the others connect); the test process opens a
session of its own to inject malformed payloads and to query status and liveliness. Processes are
stopped by PID.

What this proves:
- detections arrive: one Detections message per frame the bridge processed (the status's
  `processed` count), with the input's sequence number and the camera's source timestamp, in frame
  `ref`, and the boxes equal what core.pipeline.moving_objects gives for the same pair of frames
  (the previous processed frame and this one, over their capture times' interval — the synthetic
  world's 0.2 s per frame, while the camera sends at 2 Hz; the frames are regenerated here from the same
  seed);
- the detections are moving cars: the bundle's modules are freshly initialised, i.e. the flow and
  egomotion modules are plain correlators (tests/stream_bundles.py), and at least one published box
  lies within 2 m of the centre of a car that truly moves in that pair (ground truth regenerated here).
- malformed payloads (garbage bytes, a Frame failing validation, a Frame naming another camera) and
  a publisher restart (the camera process stopped and a new one started) do not stop the bridge;
  they are counted, and frames after them are processed;
- the accounting identity received = processed + dropped + malformed + processing_errors holds once
  idle (no processing errors), and every sample sent reached `received`;
- the status queryable and the liveliness token answer; the token goes when the bridge stops.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import zenoh

from n3dmap.v1 import types_pb2
from services.streaming import keys
from services.streaming.session import ZenohOptions, open_session

ROOT = Path(__file__).resolve().parents[2]
BRIDGE_ID = "itest"
# m/s: the bridge's --min-object-speed. The untrained correlators' flow is slow (the movers of this scene come
# out at ~0.7 m/s over the camera's 0.2 s steps), under the default 1.0 m/s, so the default would publish no
# boxes to compare; the flag is the user's lever for such a bundle.
OBJECT_SPEED = 0.5
FRAME_DT = 0.35   # the bridge's fallback clock for frames with neither capture times nor timestamps
MOVERS_SEED = 1  # a first scene whose moving cars the camera (view 0 of the rig) sees
pytestmark = [pytest.mark.integration, pytest.mark.slow]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class StreamProcess:
    """One `n3dmap stream ...` subprocess; output to a file; stopped by PID."""

    def __init__(self, args: list[str], log_dir: Path, name: str) -> None:
        self.out_path, self.err_path = log_dir / f"{name}.out", log_dir / f"{name}.err"
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p),
               "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
        with open(self.out_path, "wb") as out, open(self.err_path, "wb") as err:
            self.proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "stream", *args], cwd=ROOT,
                                         env=env, stdout=out, stderr=err)

    def stdout(self) -> str:
        return self.out_path.read_text(errors="replace")

    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"process {self.proc.args} still running after {timeout_s} s: {self.stderr()[-2000:]}")

    def stop(self, timeout_s: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def wait_for(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def make_bundle(out: Path) -> Path:
    from tests.stream_bundles import untrained_stream_bundle

    return untrained_stream_bundle("tiny", out, provenance={"test": "stream bridge"})


class Net:
    """The test's own zenoh session next to the bridge: status, liveliness, injected payloads."""

    def __init__(self, endpoint: str) -> None:
        self.session = open_session(ZenohOptions(mode="peer", connect=(endpoint,)))

    def status(self) -> dict | None:
        for reply in self.session.get(keys.bridge_status(BRIDGE_ID), timeout=5.0):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None

    def alive(self) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get(keys.bridge_token("*"), timeout=2.0)
                if r.ok is not None]

    def camera(self, camera: str) -> dict:
        return (self.status() or {}).get("cameras", {}).get(camera, {})

    def wait_idle(self, camera: str, timeout_s: float = 120.0) -> dict:
        """The camera's counters once nothing is pending and they stopped changing."""
        last = {}

        def settled():
            nonlocal last
            now = self.camera(camera)
            done = now and now["pending"] == 0 and now == last
            last = now
            return now if done else None
        return wait_for(settled, timeout_s, f"camera {camera} to go idle")

    def close(self) -> None:
        self.session.close()


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stream")
    bundle = make_bundle(tmp / "bundle")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bridge = StreamProcess(["bridge", "--bundle", str(bundle), "--listen", endpoint, "--bridge-id", BRIDGE_ID,
                            "--threads", "1", "--device", "cpu", "--min-score", "-1", "--status-every", "0",
                            "--min-object-speed", str(OBJECT_SPEED),
                            # not the world's 0.2 s: a pair timed by sequence numbers would show it
                            "--frame-dt", str(FRAME_DT)],
                           tmp, "bridge")
    net = None
    try:
        wait_for(lambda: "ready" in bridge.stderr() or bridge.proc.poll() is not None, 180, "the bridge to start")
        assert bridge.proc.poll() is None, bridge.stderr()[-3000:]
        net = Net(endpoint)
        wait_for(net.status, 30, "the bridge's status queryable")
        yield {"tmp": tmp, "bundle": bundle, "endpoint": endpoint, "bridge": bridge, "net": net}
    finally:
        if net is not None:
            net.close()
        bridge.stop()


def camera_args(camera: str, endpoint: str, *, frames: int, seed: int, rate: float = 5.0) -> list[str]:
    return ["camera", "--camera-id", camera, "--synthetic", "--preset", "tiny", "--seed", str(seed),
            "--episode-frames", "50", "--rate", str(rate), "--frames", str(frames), "--connect", endpoint]


def published(cam: StreamProcess) -> int:
    for line in cam.stderr().splitlines():
        if "published" in line:
            return int(line.split("published")[1].split()[0])
    raise AssertionError(f"camera printed no count: {cam.stderr()[-2000:]}")


def test_status_and_liveliness_answer(stack):
    net = stack["net"]
    assert keys.bridge_token(BRIDGE_ID) in net.alive()
    status = net.status()
    assert status["bridge_id"] == BRIDGE_ID and status["cameras_pattern"] == "*"
    assert status["uptime_s"] > 0 and isinstance(status["cameras"], dict)


def test_detections_arrive_and_equal_the_pipeline(stack):
    from core.pipeline import moving_objects
    from core.pipeline.moving_boxes import MovingObjectsConfig
    from services.inference.runtime import _load
    from services.inference.validation import stack_views
    from services.inference.wire import view_from_proto
    from services.inference.routes import pair_tensors
    from services.streaming.camera import encode_frame
    from services.streaming.sources import synthetic_frames
    from core.presets import get_preset
    from core.synthetic import generate_record
    from core.synthetic.config import default_world_config

    tmp, endpoint, net = stack["tmp"], stack["endpoint"], stack["net"]
    listener = StreamProcess(["listen", "--camera-id", "movers", "--json", "--connect", endpoint], tmp, "listen")
    try:
        wait_for(lambda: "subscribed" in listener.stderr(), 120, "the listener to subscribe")
        time.sleep(1.0)  # the subscription's declaration reaches the bridge before the first detections
        started = time.time()
        # replayed at 2 Hz, slower than the synthetic world's 5 Hz: motion must follow the capture clock
        camera = StreamProcess(camera_args("movers", endpoint, frames=6, seed=MOVERS_SEED, rate=2.0), tmp,
                               "camera_movers")
        assert camera.wait(180) == 0, camera.stderr()[-2000:]
        finished = time.time()
        sent = published(camera)
        counts = net.wait_idle("movers")
        lines = wait_for(lambda: (l := [json.loads(x) for x in listener.stdout().splitlines() if x.strip()])
                         and len(l) >= counts["processed"] and l, 60, "the listener to print every detection")
    finally:
        listener.stop()
    assert sent == 6 and counts["received"] == sent
    assert counts["processing_errors"] == 0
    assert counts["received"] == counts["processed"] + counts["dropped"] + counts["malformed"]
    assert len(lines) == counts["processed"] >= 2
    seqs = [d["sequence"] for d in lines]
    # A frame replaced in its slot before the worker reached it (a loaded machine) is dropped and counted:
    # every sequence the listener did not see is one of the bridge's drops, and the last one is never dropped.
    assert seqs == sorted(set(seqs)) and seqs[-1] == counts["last_sequence"] == sent - 1
    assert len(set(range(sent)) - set(seqs)) == counts["dropped"] == counts["dropped_behind"]
    # The camera marks its episode's first frame a scene start; dropped, it passes the mark to its replacement.
    assert counts["scene_starts"] == 1
    stamps = [d["source_timestamp"] for d in lines]
    assert all(started <= s <= finished for s in stamps) and stamps == sorted(stamps)
    assert all(d["frame"] == "ref" and d["camera_id"] == "movers" for d in lines)

    # The same frames again, through the pipeline in this process: pair = (previous processed, this).
    frames = synthetic_frames(preset_name="tiny", seed=MOVERS_SEED, frames_per_episode=50)
    views = [stack_views([view_from_proto(types_pb2.Frame.FromString(
        encode_frame(next(frames), camera_id="movers", sequence=i, timestamp=0.0)), "frame")], "v") for i in range(sent)]
    # as the bridge loads it: its default --egomotion-fine splat swaps the egomotion module's last stage
    bundle = _load(str(stack["bundle"]), torch.device("cpu"), egomotion_fine="splat").bundle
    assert bundle.modules["egomotion"].fine.kind == "splat"
    assert lines[0]["boxes"] == []  # a camera's first frame has nothing to compare with
    # the camera's first episode, as synthetic_frames renders it: ground truth of every pair
    record = generate_record(get_preset("tiny"), seed=MOVERS_SEED, num_views=1, num_frames=50)
    total_boxes = near_movers = 0
    torch.set_num_threads(1)
    world_dt = default_world_config(get_preset("tiny")).dt
    sent_span = lines[-1]["source_timestamp"] - lines[0]["source_timestamp"]
    assert sent_span > 1.5 * (lines[-1]["sequence"] - lines[0]["sequence"]) * world_dt  # the clocks do differ
    for before, now in zip(lines, lines[1:]):
        pair = pair_tensors([views[before["sequence"]]], [views[now["sequence"]]], torch.device("cpu"))
        with torch.inference_mode():
            # the pair spans the frames' capture clock (the world's 0.2 s per frame), not the 0.5 s per frame
            # of the replay that the timestamps (when the camera sent each frame) show
            capture_dt = (now["sequence"] - before["sequence"]) * world_dt
            ref = moving_objects(bundle, **pair, dt=capture_dt,
                                 config=MovingObjectsConfig(min_object_speed=OBJECT_SPEED))
        valid = ref["valid"][0]
        scores = ref["scores"][0][valid].numpy()
        order = np.argsort(-scores, kind="stable")
        boxes = ref["boxes"][0][valid].numpy()[order]
        got = np.array([[b[k] for k in ("x", "y", "z", "lx", "ly", "lz", "yaw")] for b in now["boxes"]]).reshape(-1, 7)
        assert got.shape == boxes.shape, (now["sequence"], got.shape, boxes.shape)
        np.testing.assert_allclose(got, boxes, atol=1e-3)
        # velocities scale with the interval: only the capture clock's gives these
        velocities = np.array([b["velocity"] for b in now["boxes"]]).reshape(-1, 3)
        np.testing.assert_allclose(velocities, ref["velocities"][0][valid].numpy()[order], atol=1e-3)
        total_boxes += len(got)
        near_movers += int((_distance_to_moving_cars(record, before["sequence"], got) < 2.0).sum())
    assert total_boxes > 0
    assert near_movers >= 1, f"none of {total_boxes} boxes lies within 2 m of a moving car"


def _distance_to_moving_cars(record: dict, t: int, boxes: np.ndarray) -> np.ndarray:
    """Distance (m) from each box centre (K×7 in ref = the camera at step t) to the nearest centre of a
    car moving from t to t+1 (core.eval.moving_protocol's ground truth); inf without one."""
    from core.eval.moving_protocol import gt_moving_boxes
    from core.geometry import se3
    from core.presets import get_preset

    gt = np.asarray(gt_moving_boxes(record, t, get_preset("tiny").grid, min_points=10)).reshape(-1, 7)
    if len(gt) == 0 or len(boxes) == 0:
        return np.full(len(boxes), np.inf)
    cam_T_ref = (se3.invert(torch.as_tensor(record["world_T_cam"][t, 0], dtype=torch.float64))
                 @ torch.as_tensor(record["world_T_ref"][t], dtype=torch.float64))  # 4×4
    centres = se3.apply(cam_T_ref[None], torch.as_tensor(gt[:, :3])[None])[0].numpy()  # G×3 in the camera
    return np.linalg.norm(boxes[:, None, :3] - centres[None], axis=2).min(axis=1)  # K


def test_malformed_payloads_and_publisher_restart_do_not_stop_the_bridge(stack):
    from services.streaming.camera import encode_frame
    from services.streaming.sources import synthetic_frames

    tmp, endpoint, net, bridge = stack["tmp"], stack["endpoint"], stack["net"], stack["bridge"]
    key = keys.rgbd("faulty")
    good = encode_frame(next(synthetic_frames(preset_name="tiny", seed=2)), camera_id="faulty", sequence=0,
                        timestamp=time.time())
    bad_frame = types_pb2.Frame.FromString(good)
    bad_frame.depth.Clear()  # decodes as a Frame, fails validation (no depth)
    wrong_camera = types_pb2.Frame.FromString(good)
    wrong_camera.camera_id = "someone_else"
    injected = [b"\x00\xffnot a protobuf at all", bad_frame.SerializeToString(), wrong_camera.SerializeToString()]
    for payload in injected:
        net.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        # one at a time, so none replaces another in the bridge's one-frame slot
        wait_for(lambda n=injected.index(payload) + 1: net.camera("faulty").get("malformed", 0) >= n, 60,
                 "the malformed payload to be counted")

    first = StreamProcess(camera_args("faulty", endpoint, frames=1000, seed=4), tmp, "camera_faulty_1")
    wait_for(lambda: net.camera("faulty").get("processed", 0) >= 2, 180, "two frames of the first camera")
    assert first.stop() == 0, first.stderr()[-2000:]  # SIGTERM: the camera ends its stream and exits 0
    sent_first = published(first)
    before = net.wait_idle("faulty")
    second = StreamProcess(camera_args("faulty", endpoint, frames=3, seed=5), tmp, "camera_faulty_2")
    assert second.wait(180) == 0, second.stderr()[-2000:]
    after = net.wait_idle("faulty")

    assert bridge.proc.poll() is None, bridge.stderr()[-3000:]
    assert after["malformed"] == len(injected) and after["processing_errors"] == 0
    assert after["publisher_restarts"] == 1
    assert after["processed"] > before["processed"]  # frames after the restart were processed
    assert after["received"] == len(injected) + sent_first + published(second)
    assert after["received"] == after["processed"] + after["dropped"] + after["malformed"]
    assert after["dropped_out_of_order"] == 0  # the restart (sequence back at 0) is not read as out of order
    assert keys.bridge_token(BRIDGE_ID) in net.alive()


def test_bridge_stops_cleanly_and_its_token_goes(stack):
    net, bridge = stack["net"], stack["bridge"]
    assert bridge.stop() == 0, bridge.stderr()[-3000:]
    final = json.loads(bridge.stdout().strip().splitlines()[-1])["final_status"]
    for camera, c in final["cameras"].items():
        assert c["received"] == (c["processed"] + c["dropped"] + c["malformed"] + c["processing_errors"]
                                 + c["pending"]), camera
    wait_for(lambda: keys.bridge_token(BRIDGE_ID) not in net.alive(), 20, "the liveliness token to go")
