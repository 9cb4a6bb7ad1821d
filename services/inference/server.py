"""Both transports in one process: uvicorn serves the FastAPI app, whose lifespan starts the runtime
and the grpc.aio server on the same event loop.

Signals: SIGTERM/SIGINT shut down gracefully within one deadline, `drain_s` from the signal: gRPC health
turns NOT_SERVING and the gRPC server stops taking calls and finishes its open ones while uvicorn, at the same
time, stops accepting and finishes open HTTP requests; then the runtime drains its queue with what is left
(a model call running at the deadline still finishes: it cannot be interrupted). SIGHUP reloads the bundle
from its directory (the old bundle keeps serving if that fails).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import socket
import sys
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Awaitable, Callable

from grpc_health.v1 import health_pb2

from core.errors import BundleError, N3dmapError
from services.inference.grpc_server import start_grpc_server
from services.inference.rest import DEFAULT_MAX_BODY, create_app
from services.inference.runtime import Runtime, RuntimeConfig
from services.malloc import limit_arenas

log = logging.getLogger("n3dmap.serve")


class ServeStartError(N3dmapError):
    """The server could not start: a port is taken or cannot be bound on the host."""


@dataclass(frozen=True)
class ServeSettings:
    runtime: RuntimeConfig
    host: str = "127.0.0.1"
    http_port: int = 8000
    grpc_port: int = 50051
    token: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    max_body_bytes: int = DEFAULT_MAX_BODY
    drain_s: float = 10.0
    log_level: str = "info"


class ShutdownDeadline:
    """One deadline for every phase of a graceful shutdown, `drain_s` from its start. The phases ran one after
    another with `drain_s` each (uvicorn's requests, gRPC's grace, the runtime's queue), so a shutdown could take
    3 × `--drain`, past the Kubernetes grace period sized for one (deploy/k8s/inference.yaml)."""

    def __init__(self, drain_s: float):
        self.drain_s = drain_s
        self.started: float | None = None
        # awaited when the shutdown starts: work that must begin then (draining the other transport)
        self.on_start: Callable[[], Awaitable[None]] | None = None

    async def start(self) -> None:
        if self.started is not None:
            return
        self.started = time.monotonic()
        if self.on_start is not None:
            await self.on_start()

    def left(self) -> float:
        """Seconds left to the deadline (the whole drain if the shutdown has not started: a failed startup)."""
        if self.started is None:
            return self.drain_s
        return max(0.0, self.drain_s - (time.monotonic() - self.started))


def build_app(settings: ServeSettings, runtime: Runtime, shutdown: ShutdownDeadline | None = None):
    """The FastAPI app whose lifespan also runs the gRPC server (and the SIGHUP reload handler); `shutdown` is the
    deadline the server's shutdown starts (`run`), so that gRPC drains beside uvicorn rather than after it."""
    shutdown = shutdown or ShutdownDeadline(settings.drain_s)
    cert = Path(settings.tls_cert).read_bytes() if settings.tls_cert else None
    key = Path(settings.tls_key).read_bytes() if settings.tls_key else None

    @asynccontextmanager
    async def lifespan(app):
        await runtime.start()
        try:
            server, port, health = await start_grpc_server(
                runtime, host=settings.host, port=settings.grpc_port, token=settings.token,
                tls_cert=cert, tls_key=key)
        except Exception as e:
            await runtime.stop(drain_s=0)
            raise OSError(f"gRPC server failed to start on {settings.host}:{settings.grpc_port}: {e}") from e
        app.state.grpc_port = port
        loop = asyncio.get_running_loop()
        grpc_drain: asyncio.Task | None = None

        async def drain_grpc() -> None:
            """Turn health NOT_SERVING and start gRPC's drain (once), as a task that runs beside uvicorn's."""
            nonlocal grpc_drain
            if grpc_drain is not None:
                return
            for name in ("", "n3dmap.v1.Inference"):
                await health.set(name, health_pb2.HealthCheckResponse.NOT_SERVING)
            grpc_drain = asyncio.create_task(server.stop(grace=shutdown.left()))

        shutdown.on_start = drain_grpc

        async def reload_on_signal():
            try:
                await runtime.reload()
            except BundleError as e:
                log.error("SIGHUP reload failed: %s", e)

        loop.add_signal_handler(signal.SIGHUP, lambda: loop.create_task(reload_on_signal()))
        scheme = "https" if cert else "http"
        print(f"n3dmap serve: bundle {runtime.version} on {runtime.device}; REST {scheme}://{settings.host}:"
              f"{settings.http_port}  gRPC {settings.host}:{port}  routes: {', '.join(runtime.routes)}",
              file=sys.stderr, flush=True)
        try:
            yield
        finally:
            loop.remove_signal_handler(signal.SIGHUP)
            await shutdown.start()   # started already when uvicorn shut down; here when the app is stopped otherwise
            await drain_grpc()
            await grpc_drain
            await runtime.stop(drain_s=shutdown.left())
            print("n3dmap serve: stopped", file=sys.stderr, flush=True)

    return create_app(runtime, token=settings.token, max_body_bytes=settings.max_body_bytes, lifespan=lifespan)


def _server_class(deadline: ShutdownDeadline):
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn re-raises a captured SIGTERM after its graceful shutdown, so the process would end
        "killed by SIGTERM"; a completed graceful shutdown exits 0 instead (SIGINT still interrupts). Its
        shutdown starts `deadline`, which starts gRPC's drain beside uvicorn's."""

        async def shutdown(self, sockets=None):
            await deadline.start()
            await super().shutdown(sockets)

        @contextlib.contextmanager
        def capture_signals(self):
            with super().capture_signals():
                yield
                self._captured_signals = [s for s in self._captured_signals if s != signal.SIGTERM]

    return Server


def run(settings: ServeSettings) -> int:
    """Serve until SIGTERM/SIGINT. Errors in the bundle or ports end the process with a message."""
    import uvicorn

    limit_arenas()  # services.malloc: RSS stayed flat under the soak's 64 clients
    # keep_heap() is not for the server: requests of every size fragment a heap that is never trimmed
    # (bench_soak.py: RSS +9.8 % in 60 s with it, the limit is 5 %)

    if bool(settings.tls_cert) != bool(settings.tls_key):
        raise BundleError("--tls-cert and --tls-key go together")
    # Both ports are checked before the bundle loads: uvicorn reports a bind error as a log line plus
    # exit status 3, and a gRPC bind error from inside the app's startup as a logged traceback.
    check_port_free(settings.host, settings.http_port, "--http-port")
    check_port_free(settings.host, settings.grpc_port, "--grpc-port")
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    sockets = None
    if settings.http_port == 0:
        # Any free port: bound here, before the app is built, because the startup line (printed from the
        # lifespan, which uvicorn runs before it binds) must name the port the OS chose, not 0.
        try:
            sock = uvicorn.Config(app=None, host=settings.host, port=0).bind_socket()
        except SystemExit:  # uvicorn's bind_socket logs the OSError and exits 3
            raise ServeStartError(f"--http-port 0: no free port could be bound on {settings.host}") from None
        settings, sockets = replace(settings, http_port=sock.getsockname()[1]), [sock]
    runtime = Runtime(settings.runtime)
    shutdown = ShutdownDeadline(settings.drain_s)
    app = build_app(settings, runtime, shutdown)
    config = uvicorn.Config(app, host=settings.host, port=settings.http_port, log_level=settings.log_level,
                            ssl_certfile=settings.tls_cert, ssl_keyfile=settings.tls_key,
                            # ceil, not `int(drain_s) or None`: a drain of 0 (or 0.5) meant None, i.e. wait forever
                            timeout_graceful_shutdown=math.ceil(settings.drain_s), lifespan="on")
    server = _server_class(shutdown)(config)
    try:
        server.run(sockets=sockets)
    except SystemExit as e:  # uvicorn exits 3 when startup fails (a port taken since the check above)
        raise ServeStartError(f"the server did not start (uvicorn exit status {e.code}); see the log above") from None
    # uvicorn returns normally when startup fails (port taken, gRPC bind error): say so by status.
    return 0 if server.started else 1


def check_port_free(host: str, port: int, option: str) -> None:
    """ServeStartError naming `option` unless `port` can be bound on `host` now (0: any free port)."""
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise ServeStartError(f"--host {host}: cannot resolve it ({e.strerror})") from None
    family, _, _, _, address = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds: TIME_WAIT is no conflict
        try:
            probe.bind(address)
        except OSError as e:
            raise ServeStartError(f"{option} {port}: cannot listen on {host}:{port} ({e.strerror}); "
                                  "is another server using it?") from None
