"""The inference runtime: one loaded bundle, one model thread, micro-batching, hot reload.

One `Runtime` serves every transport (REST, gRPC, the zenoh bridge): they validate and decode, then
`await runtime.infer(route, input)`. Models run in a single executor thread (CPU inference is
already multi-threaded inside torch; one thread keeps batches large and threads from fighting),
under `torch.inference_mode()` entered in that thread (it is thread-local).

Reload loads the new bundle in a separate thread while the old one keeps serving, then swaps it in
between batches; if loading fails the old bundle stays and the error is kept in `last_reload_error`.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
import json
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from core.device import resolve_device
from core.errors import BundleError
from core.models.egomotion_fine import FineAlignment
from core.pipeline.moving_boxes import DEFAULT_DT, MovingObjectsConfig
from services.inference.batching import BatchConfig, BatchStats, MicroBatcher
from services.inference.codecs import MAX_REQUEST_PIXELS
from services.inference.errors import ModuleUnavailable, NotReady, RequestTimeout
from services.inference.metrics import Metrics
from services.inference.routes import BOX_FRAME, ROUTES, Route

log = logging.getLogger("n3dmap.inference")

_threads_set = False


@dataclass(frozen=True)
class RuntimeConfig:
    bundle_dir: str
    device: str = "auto"                 # "cpu", "cuda", "cuda:1", or "auto" (cuda if available)
    num_threads: int | None = None       # torch intra-op threads; None = torch's default
    max_batch: int = 8
    max_wait_ms: float = 2.0
    max_queue: int = 64
    timeout_s: float = 30.0              # per-request deadline (queue + model)
    # Seconds per sequence number for moving-object pairs whose frames carry no capture times or timestamps.
    frame_dt: float = DEFAULT_DT
    # The moving-object post-processing of the moving_objects route and the gRPC stream (`serve --size-prior`,
    # `--min-object-speed`); its `dt` is unused (each pair's interval comes from its frames or frame_dt).
    moving_objects: MovingObjectsConfig = field(default_factory=MovingObjectsConfig)
    # Which last, weightless alignment stage the bundle's egomotion module runs (core/models/egomotion_fine.py;
    # `--egomotion-fine`): "module" its own, "splat" the splat stage on a 2× finer grid (fast), "off" none.
    egomotion_fine: str = "module"
    # The pixels one request may decode over all its images (`serve --max-request-pixels`; codecs.PixelBudget).
    max_request_pixels: int = MAX_REQUEST_PIXELS

    def __post_init__(self) -> None:
        if not self.max_request_pixels >= 1:
            raise BundleError(f"max_request_pixels must be at least 1, got {self.max_request_pixels}")
        if not self.frame_dt > 0:
            raise BundleError(f"frame_dt must be positive seconds, got {self.frame_dt}")
        if isinstance(self.egomotion_fine, bool):  # the option was a boolean until session 25: True = its own stage
            object.__setattr__(self, "egomotion_fine", "module" if self.egomotion_fine else "off")
        if self.egomotion_fine not in ("module", "splat", "off"):
            raise BundleError(f"egomotion_fine must be module, splat or off, got {self.egomotion_fine!r}")


@dataclass(frozen=True)
class Answer:
    """A route's result plus what every response reports."""

    result: Any
    bundle_version: str
    frame: str
    stats: BatchStats


@dataclass(frozen=True)
class _Loaded:
    bundle: Any
    version: str
    path: str
    loaded_at: float
    generation: int = 0   # which load of this process: tells apart two loads of one version (weights replaced in place)


def bundle_version(bundle) -> str:
    return str(getattr(bundle, "version", None) or "unversioned")


def _missing(route: Route, bundle, item: Any | None = None) -> list[str]:
    """The bundle modules `route` (for `item`, with its options) needs and `bundle` lacks."""
    return [m for m in route.needs(item) if m not in bundle.modules]


_LOAD_GENERATIONS = itertools.count(1)   # _Loaded.generation


def _load(path: str, device: torch.device, *, egomotion_fine: str = "module") -> _Loaded:
    from core.bundle import load_bundle  # safetensors / weights_only: no code is unpickled

    bundle = load_bundle(path, device)
    for module in bundle.modules.values():
        module.eval()
    ego = bundle.modules.get("egomotion")
    if ego is not None and getattr(ego, "fine", None) is not None:
        if egomotion_fine == "off":
            ego.fine = None  # no fine stage: every pipeline path then skips it
        elif egomotion_fine == "splat":
            ego.fine = FineAlignment(kind="splat", factor=2)
    return _Loaded(bundle=bundle, version=bundle_version(bundle), path=str(path), loaded_at=time.time(),
                   generation=next(_LOAD_GENERATIONS))


class Runtime:
    """Create, `await start()`, serve with `await infer(route, input)`, `await stop()`."""

    def __init__(self, config: RuntimeConfig, *, metrics: Metrics | None = None):
        global _threads_set
        self.config = config
        self.metrics = metrics or Metrics()
        self.device = resolve_device(config.device)
        if config.num_threads and not _threads_set:
            torch.set_num_threads(config.num_threads)  # once per process: torch warns on a second call
            _threads_set = True
        self._loaded = _load(config.bundle_dir, self.device, egomotion_fine=config.egomotion_fine)
        self.last_reload_error: str | None = None
        self._model_thread = ThreadPoolExecutor(1, thread_name_prefix="n3dmap-model")
        self._reload_lock: asyncio.Lock | None = None
        self._batcher = MicroBatcher(
            self._run_batch, self._model_thread,
            config=BatchConfig(max_batch=config.max_batch, max_wait_s=config.max_wait_ms / 1000.0,
                               max_queue=config.max_queue),
            observe=lambda key, n, waits, model_s: self.metrics.observe_batch(key[0], n, waits, model_s))
        self.ready = False

    # --- lifecycle -------------------------------------------------------------------------
    async def start(self) -> None:
        self._reload_lock = asyncio.Lock()
        self._batcher.start()
        self.ready = True
        log.info("runtime ready: bundle %s (%s) on %s, routes %s", self.version, self._loaded.path,
                 self.device, ", ".join(self.routes))

    async def stop(self, drain_s: float = 10.0) -> None:
        """Refuse new requests, let in-flight ones finish (up to drain_s), stop the model thread."""
        self.ready = False
        drained = await self._batcher.drain(drain_s)
        if not drained:
            log.warning("shutdown: %d requests still in flight after %.1f s", self._batcher.in_flight, drain_s)
        await self._batcher.stop()
        self._model_thread.shutdown(wait=True)

    # --- what is loaded --------------------------------------------------------------------
    @property
    def loaded(self) -> _Loaded:
        """The current load (bundle, version, generation) as one snapshot: a reload swaps it on another thread,
        so code that needs the bundle and its identity together reads them from one `loaded`."""
        return self._loaded

    @property
    def bundle(self):
        return self._loaded.bundle

    @property
    def version(self) -> str:
        return self._loaded.version

    @property
    def modules(self) -> list[str]:
        return sorted(self._loaded.bundle.modules)

    @property
    def routes(self) -> list[str]:
        return [name for name, r in ROUTES.items() if not _missing(r, self._loaded.bundle)]

    @property
    def queued(self) -> int:
        return self._batcher.queued

    @property
    def in_flight(self) -> int:
        return self._batcher.in_flight

    def describe(self) -> dict:
        """What /v1/models and the Models RPC report."""
        bundle = self._loaded.bundle
        meta = getattr(bundle, "meta", {}) or {}
        return {"bundle_version": self.version, "bundle_path": self._loaded.path,
                "preset": bundle.preset.name, "modules": self.modules, "routes": self.routes,
                "grid": bundle.preset.grid.to_dict(), "device": str(self.device),
                "loaded_at": self._loaded.loaded_at, "last_reload_error": self.last_reload_error,
                "meta_json": json.dumps(meta, sort_keys=True, default=str)}

    def require(self, route: str, item: Any | None = None) -> Route:
        """The route, or ModuleUnavailable if the loaded bundle lacks one of the modules it (for `item`) needs."""
        r = ROUTES[route]
        missing = _missing(r, self._loaded.bundle, item)
        if missing:
            raise ModuleUnavailable(route, missing, self.version)
        return r

    # --- inference -------------------------------------------------------------------------
    async def infer(self, route: str, item: Any, *, timeout_s: float | None = None) -> Answer:
        """Validated input of `route` -> Answer. Raises the typed errors of services.inference.errors."""
        if not self.ready:
            raise NotReady("the runtime is not ready (starting, reloading state or shutting down)")
        r = self.require(route, item)
        (result, version), stats = await self._batcher.submit(
            r.batch_key(item), item, timeout_s=self.config.timeout_s if timeout_s is None else timeout_s)
        return Answer(result=result, bundle_version=version, frame=BOX_FRAME, stats=stats)

    async def call_on_model_thread(self, fn: Callable[[], Any], *, timeout_s: float | None = None) -> Any:
        """fn() on the model thread, in turn with the batches, under inference mode: work that carries state
        from call to call (a stream's per-camera cache) and so does not batch with other requests."""
        if not self.ready:
            raise NotReady("the runtime is not ready (starting, reloading state or shutting down)")

        def run():
            with torch.inference_mode():
                return fn()

        future = asyncio.get_running_loop().run_in_executor(self._model_thread, run)
        timeout = self.config.timeout_s if timeout_s is None else timeout_s   # 0: a deadline already passed
        try:
            return await asyncio.wait_for(future, timeout)
        except asyncio.TimeoutError:
            raise RequestTimeout(f"request did not finish within {timeout:g} s") from None

    def infer_sync(self, route: str, items: list) -> list:
        """In-process, unqueued call of a whole batch on the caller's thread (benchmarks, tools)."""
        r = self.require(route, items[0] if items else None)
        with torch.inference_mode():
            return r.run(self._loaded.bundle, items, self.device)

    def _run_batch(self, key, items: list) -> list:
        loaded = self._loaded  # one bundle for the whole batch, even if a reload swaps meanwhile
        route = ROUTES[key[0]]
        missing = _missing(route, loaded.bundle, items[0])
        if missing:  # a reload removed the module while the request waited
            raise ModuleUnavailable(route.name, missing, loaded.version)
        with torch.inference_mode():
            results = route.run(loaded.bundle, items, self.device)
        return [(r, loaded.version) for r in results]

    # --- reload ----------------------------------------------------------------------------
    async def reload(self, bundle_dir: str | None = None) -> dict:
        """Load `bundle_dir` (default: the current path again) and swap it in.

        On failure the old bundle keeps serving, `last_reload_error` says why, and BundleError is
        raised. Loading runs in its own thread, so requests keep being answered meanwhile.
        """
        path = str(bundle_dir or self._loaded.path)
        async with self._reload_lock:
            try:
                if not Path(path).is_dir():
                    raise BundleError(f"bundle directory {path} does not exist")
                loaded = await asyncio.get_running_loop().run_in_executor(
                    None, functools.partial(_load, path, self.device, egomotion_fine=self.config.egomotion_fine))
            except Exception as e:  # any failure to load keeps the old bundle serving
                self.last_reload_error = f"{type(e).__name__}: {e}"
                self.metrics.reloads.labels("error").inc()
                log.error("reload of %s failed; still serving %s: %s", path, self.version, self.last_reload_error)
                if isinstance(e, BundleError):
                    raise
                raise BundleError(f"reloading {path} failed: {self.last_reload_error}") from e
            old = self.version
            self._loaded = loaded
            self.last_reload_error = None
            self.metrics.reloads.labels("ok").inc()
            log.info("reloaded bundle %s -> %s from %s", old, loaded.version, path)
            return self.describe()
