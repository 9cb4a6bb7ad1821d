"""The main job, end to end on the embedded defaults (scripts/quickstart.sh runs this).

It runs the real `n3dmap` commands as subprocesses and prints each one, so every step can be
rerun by hand. Steps whose output already exists are skipped (training reruns resume instead), so
an interrupted quick start continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

CLI = [sys.executable, "-m", "services.cli.main"]


def run(args: list[str], *, title: str) -> None:
    print(f"\n== {title}\n$ n3dmap {shlex.join(args)}", flush=True)
    started = time.monotonic()
    code = subprocess.call(CLI + args)
    if code != 0:
        raise SystemExit(f"quickstart: `n3dmap {shlex.join(args)}` failed with exit status {code}")
    print(f"   ({time.monotonic() - started:.0f} s)", flush=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.quickstart", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="quickstart", help="where everything lands (default ./quickstart)")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--episodes", type=int, default=16, help="training records to generate")
    parser.add_argument("--steps", type=int, default=40, help="steps of each training job")
    parser.add_argument("--workers", type=int, default=2, help="Ray Train workers for pretraining (0 = in-process)")
    parser.add_argument("--skip-serve", action="store_true")
    parser.add_argument("--skip-stream", action="store_true")
    args = parser.parse_args(argv)

    out = Path(args.out)
    data, val, runs, reports = out / "data" / "train", out / "data" / "val", out / "runs", out / "reports"
    started = time.monotonic()

    if not (data / "manifest.json").exists():
        run(["data", "generate", "--out", str(data), "--preset", args.preset, "--episodes", str(args.episodes),
             "--seed", "0", "--moving-ego", "mixed", "--overwrite"], title="1. generate a synthetic training set")
    if not (val / "manifest.json").exists():
        run(["data", "generate", "--out", str(val), "--preset", args.preset, "--episodes", "4", "--seed", "1",
             "--split", "val", "--moving-ego", "mixed", "--overwrite"], title="   and a validation set")
    run(["data", "info", str(data), "--verify"], title="   verify it")
    run(["data", "preview", str(data), "--out", str(out / "preview.png")], title="   preview one record")

    steps = str(args.steps)
    run(["train", "pretrain", "--data", str(data), "--run-dir", str(runs / "pretrain"), "--objective", "contrastive",
         "--workers", str(args.workers), "--steps", steps],
        title=f"2. view-contrastive pretraining on a {args.workers}-worker local Ray")
    previous = runs / "pretrain" / "bundle"
    for task in ("egomotion", "occupancy", "flow"):
        run(["train", task, "--data", str(data), "--run-dir", str(runs / task), "--init", str(previous),
             "--workers", "0", "--steps", steps], title=f"3. train {task} (warm start from {previous.parent.name})")
        previous = runs / task / "bundle"
    run(["train", "detector", "--data", str(data), "--run-dir", str(runs / "detector"), "--init", str(previous),
         "--labels", str(args.episodes), "--workers", "0", "--steps", steps], title="   train the 3D detector")
    bundle = runs / "detector" / "bundle"
    run(["bundle", "info", str(bundle)], title="   the final bundle")

    run(["eval", "all", "--data", str(val), "--bundle", str(bundle), "--out", str(reports / "all")],
        title="4. evaluate every module on the validation set")

    if not args.skip_serve:
        serve_and_call(bundle, data)
    recording = None
    if not args.skip_stream:
        recording = stream(bundle, out, size_prior=model_size_prior(reports / "all"))

    print(f"\nquickstart finished in {time.monotonic() - started:.0f} s; everything is under {out}/:"
          f"\n  {out}/preview.png, {runs}/*/metrics.jsonl, {bundle}, {reports}/all/report.md"
          + (f", {recording} (open it with `rerun {recording}`)" if recording else ""), flush=True)
    return 0


def serve_and_call(bundle: Path, data: Path) -> None:
    """5. Start `n3dmap serve`, call every route over REST and gRPC with the Python client, stop it."""
    from core.data.shards import ShardDataset
    from services.inference.client import Frames, GrpcClient, RestClient

    http_port, grpc_port = free_port(), free_port()
    cmd = ["serve", "--bundle", str(bundle), "--http-port", str(http_port), "--grpc-port", str(grpc_port)]
    print(f"\n== 5. serve the bundle over REST + gRPC\n$ n3dmap {shlex.join(cmd)} &", flush=True)
    server = subprocess.Popen(CLI + cmd)
    try:
        rest = RestClient(f"http://127.0.0.1:{http_port}")
        deadline = time.monotonic() + 180
        while True:
            try:
                if rest.health()["ready"]:
                    break
            except Exception:  # not listening yet
                pass
            if server.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("quickstart: the inference server did not become ready")
            time.sleep(0.5)
        record = ShardDataset(str(data))[0]
        # All views of the record at t=0 and t=1: rgb V×H×W×3, depth V×H×W, poses V×4×4.
        views0 = Frames(record["rgb"][0], record["depth"][0], record["pix_T_cam"], record["world_T_cam"][0])
        views1 = Frames(record["rgb"][1], record["depth"][1], record["pix_T_cam"], record["world_T_cam"][1])
        grpc_client = GrpcClient(f"127.0.0.1:{grpc_port}")
        for name, client in (("REST", rest), ("gRPC", grpc_client)):
            models = client.models()
            print(f"   {name}: bundle {models['bundle_version']}, routes {', '.join(models['routes'])}")
            m = client.map(views0)
            print(f"   {name} map: occupancy {list(m['occupancy'].shape)}, "
                  f"{int((m['occupancy'] > 0.5).sum())} voxels occupied")
            e = client.egomotion(views0, views1)
            print(f"   {name} egomotion: cam0_T_cam1 translation {e['cam0_T_cam1'][:3, 3].round(3).tolist()} m")
            f = client.flow(views0, views1)
            print(f"   {name} flow: {list(f['flow'].shape)}")
            d = client.detect(views0)
            print(f"   {name} detect: {len(d['boxes'])} boxes in {d['frame']}")
            mo = client.moving_objects(views0, views1)
            print(f"   {name} moving-objects: {len(mo['boxes'])} boxes in {mo['frame']}")
        grpc_client.close()
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def rerun_installed() -> bool:
    """Whether the viz extra (rerun-sdk) is importable: the stream step then also records stream.rrd."""
    import importlib.util

    return importlib.util.find_spec("rerun") is not None


def model_size_prior(eval_all_dir: Path) -> list[float] | None:
    """[length, width, height] (metres) of the amodal size prior that step 4's `eval moving` estimated,
    without labels, from the model's own moving components on the validation pairs; None if it found none."""
    import json

    try:
        metrics = json.loads((eval_all_dir / "metrics.json").read_text())["metrics"]
        prior = metrics["moving"]["size_priors"]["3d (model)"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return None if prior is None else [round(prior[k], 2) for k in ("length", "width", "height")]


# The stream step's map placement (README: Live streams): 16 m ahead of the camera, over the synthetic
# world's ground plane, which core.synthetic puts at world y = the rendering preset's ground_y (Y down;
# `stream camera --synthetic` renders the tiny preset by default).
STREAM_LEVEL_AHEAD_M = 16.0


def stream(bundle: Path, out_dir: Path, *, size_prior: list[float] | None = None) -> Path | None:
    """6. Bridge + simulated camera + listener over zenoh on loopback (peer mode), and with the viz
    extra a `stream view` recording everything to OUT/stream.rrd. Returns that recording's path.
    size_prior: the bridge's amodal box size (from step 4's evaluation), or None for visible boxes."""
    from core.presets import TINY  # the synthetic camera's preset: its ground is the world's y = ground_y

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    frames = 16
    recording = out_dir / "stream.rrd" if rerun_installed() else None
    bridge_cmd = ["stream", "bridge", "--bundle", str(bundle), "--listen", endpoint, "--duration", "300",
                  "--bridge-id", "quickstart", "--status-every", "0",
                  # maps placed over the synthetic street as the training grids are (its ground: world y = 2)
                  "--level", "--level-ahead", str(STREAM_LEVEL_AHEAD_M), "--ground-y", str(TINY.ground_y),
                  *(["--size-prior", *map(str, size_prior)] if size_prior else [])]
    listen_cmd = ["stream", "listen", "--camera-id", "cam0", "--connect", endpoint]
    view_cmd = ["stream", "view", "--camera-id", "cam0", "--connect", endpoint, "--save", str(recording)]
    camera_cmd = ["stream", "camera", "--camera-id", "cam0", "--synthetic", "--rate", "5", "--frames", str(frames),
                  "--connect", endpoint]
    print("\n== 6. stream a simulated camera through the zenoh bridge"
          + (" (and record it for the 3D viewer)" if recording else ""), flush=True)
    for cmd in (bridge_cmd, listen_cmd, *([view_cmd] if recording else []), camera_cmd):
        print(f"$ n3dmap {shlex.join(cmd)} &", flush=True)
    bridge = subprocess.Popen(CLI + bridge_cmd, stdout=subprocess.PIPE, text=True)
    listener = subprocess.Popen(CLI + listen_cmd)
    view, view_log = None, out_dir / "stream_view.log"
    if recording:
        with open(view_log, "wb") as log:
            view = subprocess.Popen(CLI + view_cmd, stderr=log)
    try:
        time.sleep(2.0)
        if view is not None:
            wait_for_line(view, view_log, "viewer: subscribed", timeout_s=300)
        code = subprocess.call(CLI + camera_cmd)
        if code != 0:
            raise SystemExit(f"quickstart: the simulated camera failed with exit status {code}")
        wait_until_bridge_idle(endpoint, bridge_id="quickstart", camera="cam0", frames=frames)
        time.sleep(0.5)  # the last detections are on their way to the listener and the view
    finally:
        for proc in (listener, view, bridge):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        out, _ = bridge.communicate(timeout=60)
        listener.wait(timeout=30)
        if view is not None:
            view.wait(timeout=60)
    if view is not None:
        if view.returncode != 0:
            raise SystemExit(f"quickstart: `n3dmap stream view` failed with exit status {view.returncode}; "
                             f"see {view_log}")
        summary = [line for line in view_log.read_text().splitlines() if line.startswith("viewer: logged")]
        size = recording.stat().st_size / 2**20
        print(f"   {summary[-1] if summary else 'viewer: (no summary)'} ({size:.1f} MB)", flush=True)
    report_bridge_accounting(out)
    return recording


def wait_for_line(proc: subprocess.Popen, log: Path, text: str, *, timeout_s: float) -> None:
    """Until `text` appears in the process's log (it exited or the time ran out: an error)."""
    deadline = time.monotonic() + timeout_s
    while text not in log.read_text(errors="replace"):
        if proc.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"quickstart: `n3dmap {shlex.join(proc.args[3:])}` did not print {text!r}; see {log}")
        time.sleep(0.1)


def report_bridge_accounting(out: str) -> None:
    for line in out.splitlines():
        if line.startswith('{"final_status"'):
            status = json.loads(line)["final_status"]["cameras"].get("cam0", {})
            print(f"   bridge accounting for cam0: received {status.get('received')}, processed "
                  f"{status.get('processed')}, dropped {status.get('dropped')}, malformed {status.get('malformed')}, "
                  f"errors {status.get('processing_errors')}, scene_starts {status.get('scene_starts')}; "
                  f"latency p50 {_ms(status.get('latency_ms', {}).get('p50'))} ms", flush=True)


def _ms(value) -> str:
    return f"{value:.0f}" if isinstance(value, (int, float)) else str(value)


def wait_until_bridge_idle(endpoint: str, *, bridge_id: str, camera: str, frames: int, timeout_s: float = 120) -> None:
    """Ask the bridge's status queryable until every frame sent has reached a final bucket."""
    from services.streaming import keys
    from services.streaming.session import ZenohOptions, open_session

    session = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for reply in session.get(keys.bridge_status(bridge_id), timeout=2.0):
                if reply.ok is not None:
                    stats = json.loads(reply.ok.payload.to_bytes())["cameras"].get(camera, {})
                    if stats.get("received") == frames and stats.get("pending") == 0:
                        return
            time.sleep(0.2)
    finally:
        session.close()


if __name__ == "__main__":
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    sys.exit(main())
