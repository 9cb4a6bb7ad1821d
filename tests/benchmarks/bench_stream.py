"""Benchmark of the zenoh stream bridge: sustained frames/s and camera-publish → detection-received
latency, p50/p99, per preset, with the bridge, the simulated camera and the listener as three
separate `n3dmap stream` processes on loopback (peer mode).

    python tests/benchmarks/bench_stream.py                       # tiny and small, 10 Hz, 60 frames
    python tests/benchmarks/bench_stream.py --presets tiny --rate 10 --frames 100 --threads 1
    python tests/benchmarks/bench_stream.py --bundle-tiny runs/flow/bundle

Without --bundle-<preset> each preset gets freshly initialised modules (mapper, flow, egomotion;
tests/stream_bundles.py): the compute per frame does not depend on the weights, and the untrained
flow and egomotion modules are correlators that already move the synthetic cars, so the box stage
sees realistic work (the box stage costs more with a noisy flow: it was 12 ms at tiny with random
flow weights, under 1 ms with these). Latency is measured by the listener (its receive time minus
the camera's source timestamp; one host, one clock) over the frames the bridge ran the models on
(a camera's first frame has no pair and is left out). Figures printed: frames sent / processed /
dropped, sustained processed frames/s (first to last detection), latency p50/p99, the bridge's
model time per stage (its status), the bridge's CPU seconds per processed frame, and the load
average of the host before and after (the dev machine is shared: read the figures against it).

Accuracy of what the stream publishes: the camera's episode is regenerated here (the same seed and
frames, core.synthetic), and each published frame's boxes (in `ref` = the camera at the previous
processed frame, or that camera levelled to gravity with `--level`: the Detections' world_T_frame) are
matched to the cars truly moving from that frame on (core.eval.moving_protocol's ground truth), greedily by
score at 3D IoU 0.25 and 0.5 (core.eval.iou3d.iou_3d_across_frames: the boxes' frame is not the ground
truth's, so the boxes are compared across frames). Printed: precision (matched boxes /
published boxes) and recall (matched movers / true movers) over the whole run.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args: list[str], log_dir: Path, name: str) -> tuple[subprocess.Popen, Path, Path]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    out, err = log_dir / f"{name}.out", log_dir / f"{name}.err"
    with open(out, "wb") as o, open(err, "wb") as e:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "stream", *args], cwd=ROOT, env=env,
                                stdout=o, stderr=e)
    return proc, out, err


def stop(proc: subprocess.Popen, timeout_s: float = 60.0) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def wait_for(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.2)
    raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")


def cpu_seconds(pid: int) -> float:
    """utime + stime of a live process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def fresh_bundle(preset_name: str, out: Path) -> Path:
    from tests.stream_bundles import untrained_stream_bundle

    return untrained_stream_bundle(preset_name, out, provenance={"bench": "stream"})


def box_accuracy(preset: str, frames: int, lines: list[dict], ious=(0.25, 0.5)) -> dict:
    """Precision and recall of the published boxes against the regenerated episode's true movers.

    The true movers are those centred in the episode's own map grid (`gt_moving_boxes`, as the evaluation
    protocol); the bridge's grid sits elsewhere (the camera's frame, or levelled), so only published boxes
    centred in the episode's grid are scored — a right box beyond it would otherwise count as a false one
    ("outside_grid" counts the others). Velocities and speed thresholds follow the frames' capture times,
    the synthetic world's 0.2 s per frame at any --rate (before session 22 they followed the replay clock:
    at 2 Hz the bridge's speed thresholds were 2.5 × their m/s in world terms; README, "Live streams over
    zenoh")."""
    from core.eval.iou3d import iou_3d_across_frames
    from core.eval.moving_protocol import gt_moving_boxes
    from core.presets import get_preset
    from core.synthetic import generate_record

    grid = get_preset(preset).grid
    # the camera's first (and only) episode: `--seed 0 --episode-frames FRAMES`, view 0
    record = generate_record(get_preset(preset), seed=0, num_views=1, num_frames=frames)
    counts = {iou: {"tp_boxes": 0, "found_movers": 0} for iou in ious}
    published = movers = outside = 0
    lo, hi = np.asarray(grid.bounds_min), np.asarray(grid.bounds_max)
    for before, now in zip(lines, lines[1:]):
        t = before["sequence"]
        got = np.array([[b[k] for k in ("x", "y", "z", "lx", "ly", "lz", "yaw")]
                        for b in sorted(now["boxes"], key=lambda b: -b["score"])]).reshape(-1, 7)
        gt = np.asarray(gt_moving_boxes(record, t, grid, min_points=10)).reshape(-1, 7)      # in ref_t
        # the boxes' frame (the camera at frame t, or that levelled with --level) from the ground truth's ref_t
        world_T_frame = (np.asarray(now["world_T_frame"], np.float64) if now.get("world_T_frame") is not None
                         else record["world_T_cam"][t, 0].astype(np.float64))
        frame_T_ref = np.linalg.inv(world_T_frame) @ record["world_T_ref"][t].astype(np.float64)
        ref_T_frame = np.linalg.inv(frame_T_ref)
        centres = got[:, :3] @ ref_T_frame[:3, :3].T + ref_T_frame[:3, 3]                    # K×3 in ref_t
        in_grid = ((centres >= lo) & (centres < hi)).all(axis=1)                              # K
        outside += int((~in_grid).sum())
        got = got[in_grid]
        overlap = iou_3d_across_frames(got, gt, frame_T_ref)                                  # K×G
        published += len(got)
        movers += len(gt)
        for iou in ious:
            taken = np.zeros(len(gt), dtype=bool)
            for k in range(len(got)):                     # best score first
                candidates = np.where(~taken & (overlap[k] >= iou))[0]
                if len(candidates):
                    taken[candidates[np.argmax(overlap[k, candidates])]] = True
                    counts[iou]["tp_boxes"] += 1
            counts[iou]["found_movers"] += int(taken.sum())
    return {"published_boxes": published, "outside_grid": outside, "true_movers": movers,
            **{f"precision@{iou}": round(c["tp_boxes"] / published, 3) if published else None for iou, c in counts.items()},
            **{f"recall@{iou}": round(c["found_movers"] / movers, 3) if movers else None for iou, c in counts.items()}}


def run_preset(preset: str, bundle: Path, args, work: Path) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    load_before = os.getloadavg()
    bridge, bridge_out, bridge_err = start(
        ["bridge", "--bundle", str(bundle), "--listen", endpoint, "--bridge-id", f"bench-{preset}",
         "--threads", str(args.threads), "--device", "cpu", "--status-every", "0",
         *([] if args.lookahead else ["--no-lookahead"]),
         "--egomotion-fine", args.egomotion_fine,
         *([] if args.size_prior is None else ["--size-prior", *map(str, args.size_prior)]),
         *(["--level"] if args.level else []),
         *(["--level-ahead", str(args.level_ahead)] if args.level_ahead else []),
         *(["--ground-y", str(args.ground_y)] if args.ground_y is not None else [])], work, f"bridge_{preset}")
    listener = camera = None
    try:
        wait_for(lambda: "ready" in bridge_err.read_text() or bridge.poll() is not None, 300, "the bridge")
        if bridge.poll() is not None:
            raise RuntimeError(bridge_err.read_text()[-3000:])
        listener, listen_out, listen_err = start(["listen", "--camera-id", "bench", "--json", "--connect", endpoint],
                                                 work, f"listen_{preset}")
        wait_for(lambda: "subscribed" in listen_err.read_text(), 120, "the listener")
        time.sleep(1.0)
        cpu_start = cpu_seconds(bridge.pid)
        camera, _, camera_err = start(
            ["camera", "--camera-id", "bench", "--synthetic", "--preset", preset, "--seed", "0",
             "--episode-frames", str(args.frames), "--rate", str(args.rate), "--frames", str(args.frames),
             "--connect", endpoint], work, f"camera_{preset}")
        camera.wait(args.frames / args.rate + 600)
        time.sleep(args.drain_s)  # the bridge finishes the frame in hand
        cpu_used = cpu_seconds(bridge.pid) - cpu_start
    finally:
        for p in (camera, listener):
            if p is not None:
                stop(p)
        stop(bridge)
    load_after = os.getloadavg()
    final = json.loads(bridge_out.read_text().strip().splitlines()[-1])["final_status"]
    counts = final["cameras"].get("bench", {})
    decoded = [json.loads(x) for x in listen_out.read_text().splitlines() if x.strip().startswith("{")]
    lines = [d for d in decoded if "error" not in d]   # the listener prints undecodable messages as {"error": …}
    modelled = [d for d in lines if d["sequence"] != lines[0]["sequence"]] if lines else []
    e2e = np.array([d["end_to_end_ms"] for d in modelled])
    received_at = np.array([d["source_timestamp"] + d["end_to_end_ms"] / 1000.0 for d in lines])
    span = float(received_at[-1] - received_at[0]) if len(lines) > 1 else float("nan")
    return {
        "preset": preset, "rate_hz": args.rate, "threads": args.threads, "lookahead": args.lookahead,
        "sent": counts.get("received"), "processed": counts.get("processed"), "dropped": counts.get("dropped"),
        "malformed": counts.get("malformed"), "processing_errors": counts.get("processing_errors"),
        "pending": counts.get("pending"),
        "identity_holds": counts.get("received") == (counts.get("processed", 0) + counts.get("dropped", 0)
                                                      + counts.get("malformed", 0) + counts.get("processing_errors", 0)
                                                      + counts.get("pending", 0)),
        "detections_received": len(lines), "undecodable_messages": len(decoded) - len(lines),
        "sustained_fps": round((len(lines) - 1) / span, 2) if len(lines) > 1 and span > 0 else None,
        "e2e_ms_p50": round(float(np.percentile(e2e, 50)), 1) if e2e.size else None,
        "e2e_ms_p99": round(float(np.percentile(e2e, 99)), 1) if e2e.size else None,
        "e2e_ms_max": round(float(e2e.max()), 1) if e2e.size else None,
        "e2e_ms_first3": [round(float(x), 1) for x in e2e[:3]],  # the warm-up shows here
        "bridge_cpu_s_per_processed": round(cpu_used / max(1, counts.get("processed", 1)), 3),
        "bridge_cpu_s": round(cpu_used, 2),
        "stages_ms": {k: v["p50"] for k, v in final.get("stages_ms", {}).items()},
        "step_ms_p99": final.get("stages_ms", {}).get("step_total", {}).get("p99"),
        "load_before": [round(x, 2) for x in load_before], "load_after": [round(x, 2) for x in load_after],
        "boxes": box_accuracy(preset, args.frames, lines),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default="tiny,small")
    parser.add_argument("--rate", type=float, default=10.0, help="camera frames per second")
    parser.add_argument("--frames", type=int, default=60, help="frames the camera publishes per preset")
    parser.add_argument("--threads", type=int, default=1, help="the bridge's torch threads")
    parser.add_argument("--no-lookahead", dest="lookahead", action="store_false",
                        help="run the bridge without its look-ahead thread (for comparison)")
    parser.add_argument("--egomotion-fine", choices=("module", "splat", "off"), default="splat",
                        help="the bridge's --egomotion-fine (its default: splat)")
    parser.add_argument("--no-egomotion-fine", dest="egomotion_fine", action="store_const", const="off",
                        help="the same as --egomotion-fine off")
    parser.add_argument("--drain-s", type=float, default=5.0, help="wait after the last frame before stopping")
    parser.add_argument("--level", action="store_true", help="the bridge's --level: boxes in the levelled camera")
    parser.add_argument("--level-ahead", type=float, default=0.0, help="the bridge's --level-ahead (metres)")
    parser.add_argument("--ground-y", type=float, default=None, help="the bridge's --ground-y (the synthetic world: 2.0)")
    parser.add_argument("--size-prior", type=float, nargs=3, default=None, metavar=("L", "W", "H"),
                        help="the bridge's --size-prior (amodal boxes; default: the bridge's default)")
    for name in ("tiny", "small", "paper"):
        parser.add_argument(f"--bundle-{name}", default=None, help=f"bundle for the {name} preset (default: fresh)")
    args = parser.parse_args(argv)
    print(f"host: {os.cpu_count()} CPUs, load average {os.getloadavg()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_stream_") as tmp:
        work = Path(tmp)
        for preset in args.presets.split(","):
            bundle = getattr(args, f"bundle_{preset}") or fresh_bundle(preset, work / f"bundle_{preset}")
            result = run_preset(preset, Path(bundle), args, work)
            print(json.dumps(result), flush=True)
            print(f"{preset}: camera at {args.rate:g} Hz, {result['processed']}/{result['sent']} frames processed "
                  f"({result['dropped']} dropped), sustained {result['sustained_fps']} fps, end-to-end p50 "
                  f"{result['e2e_ms_p50']} ms / p99 {result['e2e_ms_p99']} ms; bridge CPU "
                  f"{result['bridge_cpu_s_per_processed']} s per processed frame; load "
                  f"{result['load_before']} -> {result['load_after']}", flush=True)
            acc = result["boxes"]
            print(f"{preset}: {acc['published_boxes']} published boxes scored ({acc['outside_grid']} more centred "
                  f"outside the episode's grid), {acc['true_movers']} true movers; precision / "
                  f"recall at 3D IoU 0.25: {acc['precision@0.25']} / {acc['recall@0.25']}, at 0.5: "
                  f"{acc['precision@0.5']} / {acc['recall@0.5']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
