"""`n3dmap stream bridge|camera|listen|view`: live RGB-D over zenoh (docs/architecture.md#streaming-over-zenoh);
`view` shows one camera's stream in the Rerun viewer (services.streaming.viewer + services.viz.rerun_stream)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

from services.cli.argtypes import (DEFAULT_FRAME_DT, FRAME_DT_HELP, frame_interval, frame_rate, non_negative_float,
                                   non_negative_int, positive_float, positive_int, saliency_score)
from services.cli.egomotion_options import add_egomotion_arguments
from services.cli.moving_options import add_moving_object_arguments, moving_objects_config
from services.streaming.accounting import IDLE_EVICT_S, MAX_CAMERAS
from services.streaming.session import add_zenoh_arguments, options_from_args


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "stream", help="live RGB-D over zenoh: bridge, simulated camera, listener, 3D viewer",
        description="Stream RGB-D frames over zenoh into the bridge (egomotion → stabilised 3D flow → moving "
                    "objects) and receive its detections. Embedded default: peer mode on loopback, the bridge "
                    "listening on tcp/127.0.0.1:7447; deployment: --mode client --connect tcp/ROUTER:7447.")
    sub = parser.add_subparsers(dest="stream_command", metavar="STREAM_COMMAND", required=True)

    bridge = sub.add_parser("bridge", help="run the stream bridge over a model bundle",
                            description="Subscribe to n3dmap/<camera>/rgbd, publish n3dmap/<camera>/moving_objects "
                                        "and n3dmap/<camera>/egomotion; status JSON at n3dmap/@bridge/<id>/status.")
    bridge.add_argument("--bundle", required=True, help="model bundle directory (needs the mapper and flow modules)")
    add_zenoh_arguments(bridge, default_listen=True)
    bridge.add_argument("--cameras", default="*", metavar="PATTERN", help="glob of camera ids to serve (default: all)")
    bridge.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default)")
    bridge.add_argument("--threads", type=positive_int, default=None,
                        help="torch intra-op threads (default: CPU cores − 1, at least 1, at most 8: the "
                             "camera, listener and zenoh need a core; on a loaded 2-core host two threads "
                             "spin against each other and run ~10× slower)")
    bridge.add_argument("--min-score", type=saliency_score, default=0.0,
                        help="drop boxes whose centre-surround saliency, in [-1, 1], is below this (default 0)")
    add_moving_object_arguments(bridge)
    add_egomotion_arguments(bridge)  # the splat stage by default: a 10 Hz stream cannot pay a TSDF stage
    bridge.add_argument("--frame-dt", type=frame_interval, default=DEFAULT_FRAME_DT, metavar="S", help=FRAME_DT_HELP)
    bridge.add_argument("--level", action="store_true",
                        help="map (and box) each frame in its camera levelled to gravity (frame \"level\": the camera's "
                             "centre and heading, Y down) instead of the camera itself: upright boxes, a level "
                             "ground. Needs every frame's world_T_cam in a world whose Y points down (the "
                             "synthetic world's and n3dmap's datasets'); a frame without one counts as malformed")
    bridge.add_argument("--level-ahead", type=non_negative_float, default=0.0, metavar="M",
                        help="with --level: centre each map M metres ahead of the camera along its heading "
                             "(default 0: on the camera; the training grids sit 12-20 m from their cameras)")
    bridge.add_argument("--ground-y", type=float, default=None, metavar="Y",
                        help="with --level: the world's ground plane is Y = this (Y down); each map's centre then "
                             "sits the bundle preset's ground height above it, as in training (the synthetic "
                             "world's ground: 2.0; default: at the camera's height)")
    bridge.add_argument("--no-lookahead", dest="lookahead", action="store_false",
                        help="one worker thread only: no look-ahead thread encoding the next frame and its "
                             "egomotion beside the current step (that thread is what lets the small preset "
                             "keep up with 10 Hz on 2 cores)")
    bridge.add_argument("--idle-evict", type=positive_float, default=IDLE_EVICT_S, metavar="S",
                        help="forget a camera silent for S seconds: its state is freed, its counters go to the "
                             "status's _retired entry, and its next frame starts a scene (default %(default)g)")
    bridge.add_argument("--max-cameras", type=positive_int, default=MAX_CAMERAS, metavar="N",
                        help="cameras tracked at once; frames of one more are dropped and counted under "
                             "_too_many_cameras (default %(default)d)")
    bridge.add_argument("--bridge-id", default=None, help="id in the liveliness token and status key (default: random)")
    bridge.add_argument("--duration", type=positive_float, default=None, metavar="S",
                        help="stop after S seconds (default: run until SIGINT/SIGTERM)")
    bridge.add_argument("--status-every", type=non_negative_float, default=10.0, metavar="S",
                        help="log the accounting every S seconds (0 = never)")
    bridge.set_defaults(func=_run_bridge)

    camera = sub.add_parser("camera", help="publish frames from a dataset or the live synthetic world",
                            description="Publish n3dmap.v1.Frame messages on n3dmap/<camera>/rgbd.")
    camera.add_argument("--camera-id", required=True, help="camera id (a key-expression chunk: no '/', '*', '?', '#')")
    source = camera.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", metavar="DIR", help="replay view --view of every record of a shard dataset")
    source.add_argument("--synthetic", action="store_true", help="render the synthetic world live")
    camera.add_argument("--rate", type=frame_rate, default=10.0, metavar="HZ",
                        help="frames per second, 0.001 to 1000 (default 10)")
    camera.add_argument("--frames", type=positive_int, default=None, metavar="N", help="stop after N frames (default: endless)")
    camera.add_argument("--preset", default="tiny", help="synthetic: preset of the rendered frames (default tiny)")
    camera.add_argument("--seed", type=int, default=0, help="synthetic: first scene seed")
    camera.add_argument("--episode-frames", type=positive_int, default=8, help="synthetic: frames per scene before a new one")
    camera.add_argument("--moving-ego", action="store_true", help="synthetic: the ego (and camera) moves")
    camera.add_argument("--view", type=non_negative_int, default=0, help="dataset: which view of each record to publish")
    camera.add_argument("--loop", action="store_true", help="dataset: start over at the end")
    camera.add_argument("--capture-dt", type=frame_interval, default=None, metavar="S",
                        help="dataset: seconds between a record's frames when they were captured, sent as each "
                             "frame's capture_time so that motion is measured in capture time whatever --rate "
                             "replays it at (default: the synthetic world's step for a generated dataset, else "
                             "none: motion is then timed by when frames are sent)")
    camera.add_argument("--encoding", choices=("raw", "png"), default="raw", help="image encoding (default raw)")
    camera.add_argument("--wait-for-bridge", type=non_negative_float, default=10.0, metavar="S",
                        help="wait up to S seconds for a bridge before the first frame")
    add_zenoh_arguments(camera, default_listen=False)
    camera.set_defaults(func=_run_camera)

    listen = sub.add_parser("listen", help="print moving-object detections as they arrive")
    listen.add_argument("--camera-id", default="*", help="camera to listen to (default: every camera)")
    listen.add_argument("--json", action="store_true", help="one JSON object per line")
    listen.add_argument("--count", type=positive_int, default=None, metavar="N", help="exit after N messages")
    listen.add_argument("--timeout", type=positive_float, default=None, metavar="S", help="exit after S seconds of silence")
    add_zenoh_arguments(listen, default_listen=False)
    listen.set_defaults(func=_run_listen)

    view = sub.add_parser(
        "view", help="show a camera's frames, detections and egomotion live in the Rerun 3D viewer",
        description="Subscribe to n3dmap/<camera>/{rgbd,moving_objects,egomotion} and log them to Rerun: the "
                    "camera trajectory, the current RGB-D frame and the published boxes with their velocities, "
                    "in world (README '3D viewer (Rerun)'). Needs the viz extra: pip install -e '.[viz]'.")
    view.add_argument("--camera-id", required=True, help="camera to show (one key chunk, no wildcards)")
    sink = view.add_mutually_exclusive_group(required=True)
    sink.add_argument("--save", metavar="FILE.rrd", type=Path, help="write a recording (open it with `rerun FILE.rrd`)")
    sink.add_argument("--spawn", action="store_true", help="open a native Rerun viewer window (needs a display)")
    sink.add_argument("--serve-web", type=positive_int, metavar="PORT",
                      help="serve the Rerun web viewer on http://HOST:PORT (see --host)")
    view.add_argument("--host", default="127.0.0.1",
                      help="with --serve-web: address to bind (default 127.0.0.1, this machine only; 0.0.0.0 "
                           "serves the network)")
    view.add_argument("--grpc-port", type=positive_int, default=None,
                      help="with --serve-web: port of the viewer's data proxy (default: a free one)")
    view.add_argument("--count", type=positive_int, default=None, metavar="N",
                      help="exit after N detection messages")
    view.add_argument("--timeout", type=positive_float, default=None, metavar="S", help="exit after S seconds of silence")
    view.add_argument("--duration", type=positive_float, default=None, metavar="S", help="exit after S seconds")
    view.add_argument("--wait-for-bridge", type=non_negative_float, default=10.0, metavar="S",
                      help="after connecting, wait up to S seconds to see a bridge before announcing readiness")
    add_zenoh_arguments(view, default_listen=False)
    view.set_defaults(func=_run_view)


def default_bridge_threads() -> int:
    """Torch threads of the bridge when --threads is not given: leave one core to zenoh and the
    processes around the bridge (measured on the 2-core dev host under load: 2 threads took 2.7 s
    CPU per tiny step against 0.16 s with 1)."""
    return max(1, min(8, (os.cpu_count() or 1) - 1))


def _check_camera_id(camera_id: str, flag: str = "--camera-id") -> None:
    from services.cli.main import CliError

    if not camera_id or any(c in camera_id for c in "/*?#$ "):
        raise CliError(f"{flag} {camera_id!r} must be a single key chunk without '/', '*', '?', '#', '$' or spaces")


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _run_bridge(args: argparse.Namespace) -> int:
    from services.cli.main import CliError
    from services.inference.runtime import Runtime, RuntimeConfig
    from services.streaming.bridge import Bridge
    from services.streaming.processor import RuntimeProcessor

    if not args.level and (args.level_ahead or args.ground_y is not None):
        raise CliError("--level-ahead and --ground-y place the levelled map frame: add --level")
    if args.bridge_id is not None:   # a chunk of the bridge's token and status keys
        _check_camera_id(args.bridge_id, "--bridge-id")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stderr)
    options = _zenoh_options(args, default_listen=True)
    runtime = Runtime(RuntimeConfig(bundle_dir=args.bundle, device=args.device,
                                    num_threads=args.threads or default_bridge_threads(),
                                    egomotion_fine=args.egomotion_fine))
    try:
        processor = RuntimeProcessor(runtime, min_score=args.min_score, frame_dt=args.frame_dt,
                                     objects=moving_objects_config(args), level=args.level,
                                     level_ahead=args.level_ahead, ground_y=args.ground_y)
    except ValueError as e:
        raise CliError(str(e)) from None
    warm_s = processor.warm_up()  # before "ready": the first frames do not pay the models' one-time costs
    stop = _stop_event()
    bridge = Bridge(processor=processor, zenoh_options=options, cameras=args.cameras, bridge_id=args.bridge_id,
                    lookahead=args.lookahead, idle_evict_s=args.idle_evict, max_cameras=args.max_cameras)
    bridge.start()
    print(f"bridge {bridge.bridge_id} ready (models warmed up in {warm_s:.1f} s): bundle {runtime.version}, "
          f"modules {', '.join(runtime.modules)}, "
          f"zenoh {options.mode} listen={list(options.listen)} connect={list(options.connect)}", file=sys.stderr, flush=True)
    started = time.monotonic()
    last_status = started
    try:
        while not stop.is_set():
            if args.duration is not None and time.monotonic() - started >= args.duration:
                break
            stop.wait(0.2)
            if args.status_every and time.monotonic() - last_status >= args.status_every:
                last_status = time.monotonic()
                print(json.dumps({"status": bridge.status()}), file=sys.stderr, flush=True)
    finally:
        bridge.stop()
        print(json.dumps({"final_status": bridge.status()}), flush=True)
    return 0


def _run_camera(args: argparse.Namespace) -> int:
    from services.streaming.camera import publish_frames
    from services.streaming.sources import dataset_frames, synthetic_frames

    _check_camera_id(args.camera_id)
    options = _zenoh_options(args, default_listen=False)
    if args.synthetic:
        from core.presets import get_preset
        get_preset(args.preset)  # a bad name is a one-line error before anything starts
        frames = synthetic_frames(preset_name=args.preset, seed=args.seed, frames_per_episode=args.episode_frames,
                                  moving_ego=args.moving_ego)
    else:
        frames = dataset_frames(args.data, view=args.view, loop=args.loop, capture_dt=args.capture_dt)
    stop = _stop_event()
    sent = publish_frames(_until(frames, stop), camera_id=args.camera_id, zenoh_options=options, rate_hz=args.rate,
                          max_frames=args.frames, encoding=args.encoding, wait_for_bridge_s=args.wait_for_bridge,
                          stop=stop)
    print(f"camera {args.camera_id}: published {sent} frames", file=sys.stderr, flush=True)
    return 0


def _until(frames, stop: threading.Event):
    for frame in frames:
        if stop.is_set():
            return
        yield frame


def _run_listen(args: argparse.Namespace) -> int:
    from services.streaming.listener import listen, print_human, print_json

    if args.camera_id != "*":
        _check_camera_id(args.camera_id)
    options = _zenoh_options(args, default_listen=False)
    count = listen(zenoh_options=options, camera_id=args.camera_id, max_messages=args.count,
                   timeout_s=args.timeout, emit=print_json if args.json else print_human,
                   on_ready=lambda key: print(f"listener: subscribed to {key}", file=sys.stderr, flush=True),
                   stop=_stop_event())
    print(f"listener: received {count} detection messages", file=sys.stderr, flush=True)
    return 0


def _run_view(args: argparse.Namespace) -> int:
    from services.cli.main import CliError

    _check_camera_id(args.camera_id)
    if args.serve_web is None and (args.host != "127.0.0.1" or args.grpc_port is not None):
        raise CliError("--host and --grpc-port apply to --serve-web")
    options = _zenoh_options(args, default_listen=False)
    from services.viz.rerun_sdk import check_rrd_path, close_recording, open_recording, require_rerun

    require_rerun()
    save = check_rrd_path(args.save, flag="--save") if args.save is not None else None
    from services.streaming.viewer import view
    from services.viz.rerun_sinks import attach
    from services.viz.rerun_stream import StreamRecorder

    stop = _stop_event()
    rec = open_recording(name=f"n3dmap stream {args.camera_id}")
    viewer = attach(rec, save=save, spawn=args.spawn, serve_web=args.serve_web, host=args.host,
                    grpc_port=args.grpc_port)
    if viewer is not None and viewer.web_url:
        print(f"viewer: web viewer at {viewer.web_url} (rerun pid {viewer.pid})", file=sys.stderr, flush=True)
    elif viewer is not None:
        print(f"viewer: native viewer pid {viewer.pid}, data at {viewer.grpc_url}", file=sys.stderr, flush=True)
    try:
        recorder = StreamRecorder(recording=rec)
        counts = view(zenoh_options=options, camera_id=args.camera_id, sink=recorder, stop=stop,
                      max_detections=args.count, timeout_s=args.timeout, duration_s=args.duration,
                      wait_for_bridge_s=args.wait_for_bridge,
                      on_ready=lambda key: print(f"viewer: subscribed to {key}", file=sys.stderr, flush=True),
                      warn=lambda text: print(f"viewer: {text}", file=sys.stderr, flush=True))
    finally:
        close_recording(rec)
        if viewer is not None:
            viewer.stop()
    where = f" -> {save}" if save is not None else ""
    print(f"viewer: logged {counts.frames} frames ({counts.frames_dropped} dropped while busy), "
          f"{counts.detections} detection messages, {counts.egomotion} egomotion messages"
          + (f" ({counts.outputs_dropped} dropped while busy)" if counts.outputs_dropped else "")
          + (f", {counts.undecodable} undecodable" if counts.undecodable else "") + where, file=sys.stderr, flush=True)
    return 0


def _zenoh_options(args, *, default_listen: bool):
    from services.cli.main import CliError

    try:
        return options_from_args(args, default_listen=default_listen)
    except ValueError as e:
        raise CliError(str(e)) from None
