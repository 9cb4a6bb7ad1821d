"""A throwaway Ray head (`ray start --head --block`) owned by a test: free ports, own temp dir,
stopped by killing its process group (never `ray stop`, which would kill every Ray on the machine)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

PORT_FLAGS = ("--port", "--dashboard-port", "--ray-client-server-port", "--node-manager-port",
              "--object-manager-port", "--dashboard-agent-listen-port", "--dashboard-agent-grpc-port",
              "--runtime-env-agent-port", "--metrics-export-port")


def free_ports(n: int) -> list[int]:
    sockets = [socket.socket() for _ in range(n)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


class RayHead:
    """Start with `RayHead.start(num_cpus)`, use `.address` (job server URL), end with `.stop()`."""

    def __init__(self, proc: subprocess.Popen, address: str, temp_dir: str, log_path: Path) -> None:
        self.proc = proc
        self.address = address
        self.temp_dir = temp_dir
        self.log_path = log_path

    @staticmethod
    def start(*, num_cpus: int, timeout_s: float = 180.0) -> "RayHead":
        ports = dict(zip(PORT_FLAGS, free_ports(len(PORT_FLAGS))))
        temp_dir = tempfile.mkdtemp(prefix="n3r")  # short: Ray's unix socket paths must stay < 108 chars
        bin_dir = os.path.dirname(sys.executable)
        env = dict(os.environ, RAY_AUTH_MODE="disabled", RAY_USAGE_STATS_ENABLED="0",
                   PATH=bin_dir + os.pathsep + os.environ.get("PATH", ""))
        env.pop("RAY_ADDRESS", None)
        cmd = [os.path.join(bin_dir, "ray"), "start", "--head", "--block", f"--num-cpus={num_cpus}",
               "--dashboard-host=127.0.0.1", "--node-ip-address=127.0.0.1", "--disable-usage-stats",
               f"--temp-dir={temp_dir}", "--include-dashboard=true", f"--object-store-memory={100 * 2**20}",
               *[f"{flag}={port}" for flag, port in ports.items()]]
        log_path = Path(temp_dir) / "head.log"
        log = open(log_path, "wb")
        # Own process group: stop() kills the head and everything it started, nothing else.
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        head = RayHead(proc, f"http://127.0.0.1:{ports['--dashboard-port']}", temp_dir, log_path)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                head.stop()
                raise RuntimeError(f"ray start exited with {proc.returncode}: {log_path.read_text()[-2000:]}")
            try:
                with urllib.request.urlopen(head.address + "/api/version", timeout=2) as r:
                    if r.status == 200:
                        return head
            except OSError:
                pass
            time.sleep(1.0)
        head.stop()
        raise RuntimeError(f"Ray head did not answer at {head.address} within {timeout_s:.0f} s")

    def stop(self) -> None:
        """SIGTERM the head's process group, then SIGKILL what is left after a few seconds
        (raylet's graceful shutdown takes ~15 s and `ray start --block` may never exit on its own)."""
        pgid = self.proc.pid
        for sig, grace_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 10.0)):
            try:
                os.killpg(pgid, sig)
            except ProcessLookupError:
                break
            deadline = time.monotonic() + grace_s
            while time.monotonic() < deadline and _group_alive(pgid):
                time.sleep(0.25)
            if not _group_alive(pgid):
                break
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        shutil.rmtree(self.temp_dir, ignore_errors=True)


def _group_alive(pgid: int) -> bool:
    """Whether a live (non-zombie) process of process group `pgid` is left, read from /proc.

    Zombies count as gone: in a container without an init that reaps orphans they linger forever.
    """
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()  # after "pid (comm) ": state, ppid, pgrp, ...
        if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
            return True
    return False
