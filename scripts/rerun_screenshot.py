"""Screenshot of the Rerun viewer on a recording, without a display (how docs/images/rerun_quickstart.png
was made):

    python scripts/rerun_screenshot.py quickstart/stream.rrd docs/images/rerun_quickstart.png --frame 7

It starts the viewer headless (`rerun --headless`: no window, rendering offscreen through wgpu, which
needs a Vulkan driver — on a machine without a GPU, Mesa's software one: apt-get install
mesa-vulkan-drivers), opens the recording over the viewer's control API (rerun.experimental.ViewerClient),
moves to the given time and saves what the viewer paints; then it stops the viewer. Analytics off as
for every Rerun process n3dmap starts (services.viz.rerun_sdk.viewer_env).
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.viz.rerun_sdk import rerun_executable, viewer_env  # noqa: E402
from services.viz.rerun_sinks import _wait_listening, free_port  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("out", type=Path, help="PNG to write")
    parser.add_argument("--timeline", default="frame")
    parser.add_argument("--frame", type=int, default=None, help="sequence to show on --timeline (default: the last)")
    parser.add_argument("--size", default="1280x720", help="viewer size in logical points")
    parser.add_argument("--settle", type=float, default=8.0,
                        help="seconds to let the software renderer catch up (and the viewer's start-up toast fade)")
    parser.add_argument("--palette", action="store_true", help="re-encode as a 256-colour PNG (a third of the size)")
    args = parser.parse_args()

    from rerun.experimental import ViewerClient

    port = free_port()
    viewer = subprocess.Popen([rerun_executable(), "--headless", "--bind", "127.0.0.1", "--port", str(port),
                               "--window-size", args.size, "--hide-welcome-screen"],
                              env=viewer_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_listening(viewer, "127.0.0.1", [port], 60, "the headless Rerun viewer")
        client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
        client.open(str(args.recording.resolve()))
        if args.frame is not None:
            client.set_time(args.timeline, sequence=args.frame, play_state="paused")
        time.sleep(args.settle)  # the viewer paints asynchronously; llvmpipe is slow
        args.out.parent.mkdir(parents=True, exist_ok=True)
        client.save_screenshot(str(args.out.resolve()))
    finally:
        viewer.send_signal(signal.SIGTERM)
        try:
            viewer.wait(20)
        except subprocess.TimeoutExpired:
            viewer.kill()
            viewer.wait()
    if args.palette:
        from PIL import Image

        Image.open(args.out).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(args.out, optimize=True)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
