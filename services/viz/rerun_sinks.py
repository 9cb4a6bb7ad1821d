"""Where a live recording goes (`n3dmap stream view --save | --spawn | --serve-web`).

- `--save FILE.rrd`: a file, finalised when the command stops.
- `--spawn`: a native Rerun viewer window — the `rerun` binary started here, listening on a free
  loopback port, which the recording streams to over gRPC. It is detached: the window stays open (with
  everything received) after the command ends, and the user closes it.
- `--serve-web PORT`: the `rerun` binary as a web server — the web viewer over HTTP on PORT and a
  gRPC proxy buffering the recording for browsers that connect late — bound to `host` (127.0.0.1
  unless asked otherwise: the stream is not for the network by default). It stops with the command.

The Python SDK can host a web viewer itself, but in 0.41 its HTTP server always binds 0.0.0.0; the
`rerun` binary takes `--bind`. Every process gets rerun_sdk.viewer_env() (analytics off).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from core.errors import N3dmapError


class ViewerError(N3dmapError):
    """The Rerun viewer or web server could not be started."""


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _wait_listening(proc: subprocess.Popen, host: str, ports: list[int], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    pending = list(ports)
    while pending:
        if proc.poll() is not None:
            raise ViewerError(f"{what} exited with status {proc.returncode} before listening on {host}:{pending[0]}")
        try:
            with socket.create_connection((host, pending[0]), timeout=0.5):
                pending.pop(0)
                continue
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise ViewerError(f"{what} is not listening on {host}:{pending[0]} after {timeout_s:.0f} s")
        time.sleep(0.1)


@dataclass
class ViewerProcess:
    """A `rerun` process started for a recording: what it serves and how to stop it."""

    proc: subprocess.Popen
    grpc_url: str
    web_url: str | None = None
    stop_on_exit: bool = True

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self, timeout_s: float = 10.0) -> None:
        if not self.stop_on_exit or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _connect_host(host: str) -> str:
    """The address to reach a server bound to `host` from this machine."""
    return "127.0.0.1" if host in ("0.0.0.0", "::", "") else host


def start_web_server(*, host: str, web_port: int, grpc_port: int | None = None, timeout_s: float = 30.0) -> ViewerProcess:
    """`rerun --serve-web` bound to `host`: web viewer on `web_port`, gRPC proxy on `grpc_port` (free if None)."""
    from services.viz.rerun_sdk import rerun_executable, viewer_env

    reach = _connect_host(host)
    grpc_port = grpc_port or free_port(reach)
    cmd = [rerun_executable(), "--serve-web", "--bind", host, "--port", str(grpc_port),
           "--web-viewer-port", str(web_port)]
    # Its log goes to a file, read only when it fails to start (a pipe nobody reads would fill up and
    # block it; a closed one makes its log writes fail).
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(cmd, env=viewer_env(), stdin=subprocess.DEVNULL, stdout=log, stderr=log)
    try:
        _wait_listening(proc, reach, [grpc_port, web_port], timeout_s, "the Rerun web server")
    except ViewerError as e:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        log.seek(0)
        tail = " ".join(log.read().decode(errors="replace").split()[-40:])
        raise ViewerError(f"{e}{': ' + tail if tail else ''}") from None
    finally:
        log.close()  # the child keeps its own descriptor
    grpc_url = f"rerun+http://{reach}:{grpc_port}/proxy"
    # The page's ?url= is resolved by the browser: name the host the user reaches the page by.
    page_host = reach if host in ("0.0.0.0", "::", "") else host
    web_url = f"http://{page_host}:{web_port}/?url={quote(f'rerun+http://{page_host}:{grpc_port}/proxy', safe='')}"
    return ViewerProcess(proc=proc, grpc_url=grpc_url, web_url=web_url)


def spawn_viewer(*, timeout_s: float = 30.0) -> ViewerProcess:
    """A detached native viewer listening on a free loopback port (its window outlives the command)."""
    from services.viz.rerun_sdk import rerun_executable, viewer_env

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ViewerError("--spawn opens a window, but there is no display (DISPLAY and WAYLAND_DISPLAY are unset); "
                          "use --save FILE.rrd or --serve-web PORT")
    port = free_port()
    cmd = [rerun_executable(), "--bind", "127.0.0.1", "--port", str(port), "--expect-data-soon"]
    proc = subprocess.Popen(cmd, env=viewer_env(), stdin=subprocess.DEVNULL, start_new_session=True)
    _wait_listening(proc, "127.0.0.1", [port], timeout_s, "the Rerun viewer (is there a display?)")
    return ViewerProcess(proc=proc, grpc_url=f"rerun+http://127.0.0.1:{port}/proxy", stop_on_exit=False)


def attach(rec, *, save: Path | None = None, spawn: bool = False, serve_web: int | None = None,
           host: str = "127.0.0.1", grpc_port: int | None = None) -> ViewerProcess | None:
    """Send the recording stream `rec` to exactly one of: an .rrd file, a spawned viewer, a web server."""
    if save is not None:
        rec.save(str(save))
        return None
    viewer = spawn_viewer() if spawn else start_web_server(host=host, web_port=serve_web, grpc_port=grpc_port)
    rec.connect_grpc(viewer.grpc_url)
    return viewer
