"""`n3dmap stream view --save FILE.rrd` as a real process on a real zenoh session, fed by this test.

The test plays the camera and the bridge itself (its own peer session publishes Frame, Detections and
EgomotionResponse payloads, as services.streaming.camera and the bridge encode them), so every value
in the recording is known here: one detections entry per Detections message, at its sequence, with
its boxes, scores, speeds, velocities and frame pose; each frame's pose, image and depth; the camera
trajectory; and the egomotion chained from the first pair's given pose. The view exits by itself after
`--count` messages. The process is stopped by PID if it does not.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")

import zenoh  # noqa: E402

from n3dmap.v1 import inference_pb2, types_pb2  # noqa: E402
from services.inference import codecs  # noqa: E402
from services.streaming import keys  # noqa: E402
from services.streaming.camera import encode_frame  # noqa: E402
from services.streaming.session import ZenohOptions, open_session  # noqa: E402
from services.viz import rerun_paths as paths  # noqa: E402
from tests.rrd_reading import Recording, array, mat3, rerun_cli, yaw_from_quaternions  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CAMERA = "camA"
FRAMES = 6
pytestmark = pytest.mark.integration


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pose(i: int) -> np.ndarray:
    """world_T_cam of frame i: a camera driving forward and turning (yaw about Y)."""
    a = 0.1 * i
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    m[:3, 3] = [0.3 * i, 0.0, 1.0 * i]
    return m.astype(np.float32)


def frame(i: int) -> dict:
    rng = np.random.default_rng(i)
    K = np.eye(4, dtype=np.float32)
    K[0, 0] = K[1, 1] = 5.0
    K[0, 2], K[1, 2] = 2.5, 1.5
    return {"rgb": rng.integers(0, 256, (4, 6, 3), dtype=np.uint8),
            "depth": rng.uniform(1, 9, (4, 6)).astype(np.float32), "pix_T_cam": K, "world_T_cam": pose(i)}


def boxes_of(i: int) -> np.ndarray:
    """i-1 boxes for frame i (none for the first frame, as the bridge publishes): rows x y z lx ly lz yaw score vx vy vz."""
    rng = np.random.default_rng(100 + i)
    return rng.uniform(-2, 2, size=(max(0, i - 1), 11)).astype(np.float32)


def detections(i: int, timestamp: float) -> bytes:
    msg = types_pb2.Detections(frame="ref", camera_id=CAMERA, sequence=i, source_timestamp=timestamp,
                               bundle_version="test", world_T_frame=codecs.numpy_to_tensor(pose(max(0, i - 1))))
    for b in boxes_of(i):
        msg.boxes.append(types_pb2.Box3D(x=b[0], y=b[1], z=b[2], lx=abs(b[3]) + 1, ly=abs(b[4]) + 1, lz=abs(b[5]) + 1,
                                         yaw=b[6], frame="ref", score=abs(b[7]) / 2, label="moving",
                                         vx=b[8], vy=b[9], vz=b[10]))
    return msg.SerializeToString()


def egomotion(i: int) -> np.ndarray:
    """cam0_T_cam1 of the pair (i-1, i): the true motion plus a known error, so chaining is visible."""
    error = np.eye(4)
    error[:3, 3] = [0.05, 0.0, 0.02]
    return (np.linalg.inv(pose(i - 1).astype(np.float64)) @ pose(i) @ error).astype(np.float32)


def wait_for(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def test_view_saves_every_message_it_receives(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(ZenohOptions(mode="peer", listen=(endpoint,)))
    token = session.liveliness().declare_token(keys.bridge_token("test"))  # the view waits to see a bridge
    rrd, err_path = tmp_path / "stream.rrd", tmp_path / "view.err"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    with open(err_path, "wb") as err:
        view = subprocess.Popen([sys.executable, "-m", "services.cli.main", "stream", "view", "--camera-id", CAMERA,
                                 "--connect", endpoint, "--save", str(rrd), "--count", str(FRAMES), "--timeout", "60"],
                                cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err)
    try:
        wait_for(lambda: "viewer: subscribed" in err_path.read_text(), 60, "the view to subscribe")
        pubs = {name: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                for name, key in (("rgbd", keys.rgbd(CAMERA)), ("det", keys.moving_objects(CAMERA)),
                                  ("ego", keys.egomotion(CAMERA)))}
        wait_for(lambda: all(p.matching_status.matching for p in pubs.values()), 30, "the view's subscription")
        stamps = [time.time() - 1.0 + 0.1 * i for i in range(FRAMES)]
        for i in range(FRAMES):
            pubs["rgbd"].put(encode_frame(frame(i), camera_id=CAMERA, sequence=i, timestamp=stamps[i]))
            pubs["det"].put(detections(i, stamps[i]))
            if i > 0:
                pubs["ego"].put(inference_pb2.EgomotionResponse(
                    info=inference_pb2.ResponseInfo(bundle_version="test", frame="ref"),
                    cam0_T_cam1=codecs.numpy_to_tensor(egomotion(i))).SerializeToString())
        assert view.wait(60) == 0, err_path.read_text()
        for p in pubs.values():
            p.undeclare()
    finally:
        if view.poll() is None:
            view.send_signal(signal.SIGTERM)
            view.wait(30)
        token.undeclare()
        session.close()

    log = err_path.read_text()
    assert f"logged {FRAMES} frames" in log and f"{FRAMES} detection messages, {FRAMES - 1} egomotion messages" in log, log
    assert rerun_cli("rrd", "verify", str(rrd)).returncode == 0
    rec = Recording(rrd)
    centres = rec.at(paths.DETECTIONS, "Boxes3D:centers", paths.FRAME)
    assert sorted(centres) == list(range(FRAMES)), "one detections entry per Detections message, at its sequence"
    labels = rec.at(paths.DETECTIONS, "Boxes3D:labels", paths.FRAME)
    vectors = rec.at(paths.VELOCITIES, "Arrows3D:vectors", paths.FRAME)
    frame_poses = rec.at(paths.DETECTIONS_FRAME, "Transform3D:translation", paths.FRAME)
    latency = rec.at(paths.LATENCY, "Scalars:scalars", paths.FRAME)
    for i in range(FRAMES):
        b = boxes_of(i)
        assert np.allclose(array(centres[i], 3), b[:, :3], atol=1e-5)
        yaw = yaw_from_quaternions(rec.at(paths.DETECTIONS, "Boxes3D:quaternions", paths.FRAME)[i])
        assert np.allclose(np.angle(np.exp(1j * (yaw - b[:, 6]))), 0, atol=1e-5)
        speeds = np.linalg.norm(b[:, 8:11], axis=1)
        assert labels[i] == [f"{abs(s) / 2:.2f}, {v:.1f} m/s" for s, v in zip(b[:, 7], speeds)]
        assert np.allclose(array(vectors[i], 3), b[:, 8:11], atol=1e-5)
        assert np.allclose(array(frame_poses[i]).reshape(-1), pose(max(0, i - 1))[:3, 3], atol=1e-5)
        age_at_put_ms = 1000.0 * (1.0 - 0.1 * i)  # the stamps were that old when published
        assert age_at_put_ms - 1 < float(np.asarray(latency[i]).reshape(-1)[0]) < 60_000

    images = rec.at(paths.STREAM_IMAGE, "Image:buffer", paths.FRAME)
    depths = rec.at(paths.STREAM_IMAGE, "DepthImage:buffer", paths.FRAME)
    rotations = rec.at(paths.STREAM_CAMERA, "Transform3D:mat3x3", paths.FRAME)
    assert sorted(images) == sorted(depths) == sorted(rotations) == list(range(FRAMES))
    for i in range(FRAMES):
        assert bytes(np.asarray(images[i][0], np.uint8)) == frame(i)["rgb"].tobytes()
        assert np.asarray(depths[i][0], np.uint8).tobytes() == frame(i)["depth"].tobytes()
        assert np.allclose(mat3(rotations[i]), pose(i)[:3, :3], atol=1e-6)
    trajectory = rec.at(paths.TRAJECTORY, "LineStrips3D:strips", paths.FRAME)
    assert np.allclose(array(trajectory[FRAMES - 1][0], 3), [pose(i)[:3, 3] for i in range(FRAMES)], atol=1e-5)
    chained, expected = pose(0).astype(np.float64), [pose(0)[:3, 3]]
    for i in range(1, FRAMES):
        chained = chained @ egomotion(i)
        expected.append(chained[:3, 3])
    estimated = rec.at(paths.TRAJECTORY_EGO, "LineStrips3D:strips", paths.FRAME)
    assert sorted(estimated) == list(range(1, FRAMES))
    assert np.allclose(array(estimated[FRAMES - 1][0], 3), expected, atol=1e-4)


def _listening_addresses(port: int) -> set[str]:
    """Local IPv4/IPv6 addresses with a socket LISTENing on `port` (from /proc/net/tcp{,6})."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            local, state = line.split()[1], line.split()[3]
            address, hex_port = local.rsplit(":", 1)
            if state == "0A" and int(hex_port, 16) == port:  # 0A = LISTEN
                found.add(address)
    return found


def test_serve_web_binds_loopback_serves_the_viewer_and_stops_with_the_view(tmp_path):
    import re
    import urllib.request

    web_port, grpc_port = free_port(), free_port()
    err_path = tmp_path / "view.err"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    with open(err_path, "wb") as err:
        view = subprocess.Popen([sys.executable, "-m", "services.cli.main", "stream", "view", "--camera-id", CAMERA,
                                 "--connect", f"tcp/127.0.0.1:{free_port()}", "--serve-web", str(web_port),
                                 "--grpc-port", str(grpc_port), "--duration", "60"],
                                cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err)
    try:
        # Nothing listens at --connect: the view serves the viewer and waits for a peer.
        wait_for(lambda: "web viewer at" in err_path.read_text(), 60, "the view to start the web server")
        line = next(l for l in err_path.read_text().splitlines() if "web viewer at" in l)
        assert f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy" in line
        rerun_pid = int(re.search(r"rerun pid (\d+)", line).group(1))
        for port in (web_port, grpc_port):
            assert _listening_addresses(port) == {"0100007F"}, port  # 127.0.0.1 only
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
    finally:
        if view.poll() is None:
            view.send_signal(signal.SIGTERM)
        assert view.wait(30) == 0, err_path.read_text()
    assert not _listening_addresses(web_port) and not _listening_addresses(grpc_port)
    with pytest.raises(ProcessLookupError):
        os.kill(rerun_pid, 0)  # the web server went with the view


def test_bad_view_options_are_one_line_errors(tmp_path, capsys, monkeypatch):
    import services.cli.main as cli_main

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for extra, fragment in ((["--spawn"], "no display"),
                            (["--save", str(tmp_path)], "is a directory"),
                            (["--save", str(blocker / "s.rrd")], str(blocker / "s.rrd")),
                            (["--save", str(tmp_path / "s.rrd"), "--host", "0.0.0.0"], "--serve-web"),
                            (["--camera-id", "cam/*", "--save", str(tmp_path / "s.rrd")], "single key chunk")):
        argv = ["stream", "view", "--camera-id", CAMERA, *extra]
        code = cli_main.main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith("n3dmap stream: error: ") and fragment in err[0], (argv, err)
    assert not (tmp_path / "s.rrd").exists()
