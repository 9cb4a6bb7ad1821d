"""Helpers of the `n3dmap serve` integration tests: bundles, frames, and a real server process.

The server is a subprocess (`python -m services.cli.main serve ...`) on free ports, stopped by its
PID (SIGTERM, then SIGKILL if it does not exit).
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
# services/inference/server.py's startup line: "n3dmap serve: bundle V on D; REST http://H:P  gRPC H:P  routes: …"
STARTUP_LINE = re.compile(r"n3dmap serve: bundle .*; REST https?://[^\s]+:(?P<http>\d+)  gRPC [^\s]+:(?P<grpc>\d+)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_bundle(out_dir: Path, *, preset_name: str = "tiny", kinds: tuple[str, ...] | None = None,
                note: str = "") -> Path:
    """A real bundle (core.bundle.save_bundle) over freshly initialised modules of `preset_name`.

    `kinds` picks the modules (default: every one the training tasks export, i.e. a full bundle).
    Random weights are fine: these tests check the service, not the models.
    """
    import torch

    from core.bundle import save_bundle
    from core.presets import get_preset

    torch.manual_seed(0)
    preset = get_preset(preset_name)
    modules = fresh_modules(preset, kinds)
    save_bundle(out_dir, modules=modules, preset=preset, provenance={"test": note or "serve"}, metrics={})
    return out_dir


def fresh_modules(preset, kinds: tuple[str, ...] | None = None) -> dict:
    """Every module the registered training tasks export, freshly initialised (filtered by `kinds`)."""
    from core.tasks import TASKS, build_task

    modules = {}
    for name in TASKS:
        for kind, module in build_task(name, preset).exported_modules().items():
            modules.setdefault(kind, module)
    if kinds is not None:
        missing = set(kinds) - set(modules)
        if missing:
            raise LookupError(f"no training task exports module(s) {sorted(missing)}")
        modules = {k: v for k, v in modules.items() if k in kinds}
    return modules


def intrinsics(H: int, W: int) -> np.ndarray:
    f = W / 2.0  # 90° horizontal field of view
    return np.array([[f, 0, (W - 1) / 2, 0], [0, f, (H - 1) / 2, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float32)


def sample_frames(preset_name: str = "tiny", *, views: int = 2, seed: int = 0):
    """client.Frames of a plausible scene: ground plane depth, random colours, cameras turned about Y; the
    frame of `seed` is sequence `seed`, stamped 12.5 + 0.2·seed s."""
    from core.presets import get_preset
    from services.inference.client import Frames

    cam = get_preset(preset_name).camera
    rng = np.random.default_rng(seed)
    H, W = cam.H, cam.W
    K = intrinsics(H, W)
    v = np.arange(H, dtype=np.float32)[:, None] - (H - 1) / 2
    ground = np.where(v > 0.5, 2.0 * K[1, 1] / np.maximum(v, 0.5), 0.0)   # ground 2 m below the camera
    depth = np.broadcast_to(np.minimum(ground, 30.0), (H, W)).astype(np.float32)
    poses = []
    for i in range(views):
        a = 2 * np.pi * i / views
        T = np.eye(4, dtype=np.float32)
        T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        poses.append(T)
    return Frames(rgb=rng.integers(0, 256, (views, H, W, 3), dtype=np.uint8),
                  depth=np.stack([depth] * views), pix_T_cam=np.stack([K] * views),
                  world_T_cam=np.stack(poses), camera_id="cam0", sequence=seed,
                  timestamp=12.5 + 0.2 * seed)  # a later seed is a later frame: pairs (seed, seed + k) advance


class ServerProcess:
    """`n3dmap serve` in a subprocess; `with ServerProcess(bundle, ...) as s:` waits until ready."""

    def __init__(self, bundle: Path, *extra: str, token: str | None = None, ready_timeout_s: float = 120.0,
                 log_path: Path | None = None, os_ports: bool = False):
        """os_ports: pass `--http-port 0 --grpc-port 0` and read the ports the server chose from its startup
        line (needs `log_path`)."""
        if os_ports and log_path is None:
            raise ValueError("os_ports needs log_path: the ports are read from the server's startup line")
        self.os_ports = os_ports
        self.http_port, self.grpc_port = (0, 0) if os_ports else (free_port(), free_port())
        self.token = token
        args = [sys.executable, "-m", "services.cli.main", "serve", "--bundle", str(bundle),
                "--http-port", str(self.http_port), "--grpc-port", str(self.grpc_port), "--threads", "1",
                "--log-level", "warning", *extra]
        if token:
            args += ["--token", token]
        self.args = args
        self.ready_timeout_s = ready_timeout_s
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def target(self) -> str:
        return f"127.0.0.1:{self.grpc_port}"

    def __enter__(self) -> "ServerProcess":
        path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
        env = {**os.environ, "PYTHONPATH": path, "PYTHONUNBUFFERED": "1"}
        log = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(self.args, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        self._wait_ready()
        return self

    def _wait_ready(self) -> None:
        import httpx

        deadline = time.monotonic() + self.ready_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode} before it was ready: "
                                   f"{self.read_log()[-3000:]}")
            if self.os_ports and self.http_port == 0:
                started = STARTUP_LINE.search(self.read_log())
                if started is None:
                    time.sleep(0.2)
                    continue
                self.http_port, self.grpc_port = int(started["http"]), int(started["grpc"])
            try:
                if httpx.get(self.url + "/readyz", timeout=1.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise TimeoutError(f"server not ready within {self.ready_timeout_s} s: {self.read_log()[-3000:]}")

    def read_log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path and self.log_path.exists() else ""

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self, timeout_s: float = 30.0) -> int:
        """SIGTERM by PID and wait; SIGKILL if it does not exit in time. Returns the exit status."""
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else 0
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise

    def __exit__(self, *exc) -> None:
        self.stop()
