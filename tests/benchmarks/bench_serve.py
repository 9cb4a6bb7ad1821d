"""Benchmark of the inference service: p50/p99 latency and requests/s per route, REST vs gRPC vs an
in-process call, at the tiny and small presets, with transport overhead as % of model time.

    python tests/benchmarks/bench_serve.py [--presets tiny,small] [--requests 20] [--views 2]

For each preset it writes a bundle of freshly initialised modules (random weights: speed does not
depend on them), starts a real `n3dmap serve` process (--threads 1, --max-wait-ms 0: one client,
no batching wait) and calls each route sequentially with one client: REST with binary .npz bodies,
gRPC with raw tensors, and in-process `Runtime.infer_sync` (no transport, no queue) in this process,
also with one torch thread.

Transport overhead is measured per request, against the model time the server itself reports for that
request (`info.model_s`): overhead = p50(client latency − model_s) / p50(model_s). It covers encoding,
the wire, decoding, validation, queueing and the executor hop. (Comparing with the in-process p50
instead is noisier on a shared machine: two processes measured at different moments.)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from services.inference.client import Frames, GrpcClient, RestClient  # noqa: E402
from services.inference.routes import DetectInput, FlowInput, MapInput, MovingInput, PairInput  # noqa: E402
from services.inference.runtime import Runtime, RuntimeConfig  # noqa: E402
from services.inference.validation import make_view, stack_views  # noqa: E402
from tests.integration.serve_support import ServerProcess, make_bundle, sample_frames  # noqa: E402

ROUTES = ("map", "egomotion", "flow", "detect", "moving_objects")


def _views(f: Frames):
    f = f.batched()
    return stack_views([make_view(rgb=f.rgb[v], depth=f.depth[v], pix_T_cam=f.pix_T_cam[v],
                                  world_T_cam=f.world_T_cam[v], field=f"views[{v}]")
                        for v in range(f.rgb.shape[0])], "views")


def _client_call(client, route: str, f0: Frames, f1: Frames):
    if route == "map":
        return client.map(f0)
    if route == "detect":
        return client.detect(f0)
    return getattr(client, route)(f0, f1)


def _inproc_item(route: str, f0: Frames, f1: Frames):
    if route == "map":
        return MapInput(views=_views(f0))
    if route == "detect":
        return DetectInput(views=_views(f0))
    if route == "moving_objects":
        return MovingInput(views0=_views(f0), views1=_views(f1))
    if route == "flow":
        return FlowInput(views0=_views(f0), views1=_views(f1))  # stabilised with the poses, as the client's default
    return PairInput(views0=_views(f0), views1=_views(f1))


def _time(fn, n: int, warmup: int = 2) -> tuple[np.ndarray, np.ndarray | None]:
    """(latencies s, server-reported model seconds or None) of n sequential calls after a warm-up."""
    for _ in range(warmup):
        fn()
    latency, model = [], []
    for _ in range(n):
        t = time.perf_counter()
        out = fn()
        latency.append(time.perf_counter() - t)
        if isinstance(out, dict) and "info" in out:
            model.append(out["info"]["model_s"])
    return np.array(latency), (np.array(model) if model else None)


def bench_preset(preset: str, *, requests: int, views: int, routes: tuple[str, ...]) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_bundle(Path(tmp) / f"bundle-{preset}", preset_name=preset)
        f0, f1 = sample_frames(preset, views=views, seed=0), sample_frames(preset, views=views, seed=1)
        runtime = Runtime(RuntimeConfig(bundle_dir=str(bundle), device="cpu"))
        with ServerProcess(bundle, "--max-wait-ms", "0", "--timeout", "300") as server, \
                RestClient(server.url, timeout_s=300) as rest, GrpcClient(server.target, timeout_s=300) as grpc_c:
            available = set(rest.models()["routes"])
            for route in routes:
                if route not in available:
                    print(f"  {preset}/{route}: not in this bundle/build, skipped", flush=True)
                    continue
                item = _inproc_item(route, f0, f1)
                timings = {"in-process": _time(lambda: runtime.infer_sync(route, [item]), requests),
                           "REST": _time(lambda: _client_call(rest, route, f0, f1), requests),
                           "gRPC": _time(lambda: _client_call(grpc_c, route, f0, f1), requests)}
                for transport, (t, model) in timings.items():
                    rows.append({"preset": preset, "route": route, "transport": transport,
                                 "p50_ms": float(np.median(t)) * 1e3, "p99_ms": float(np.percentile(t, 99)) * 1e3,
                                 "rps": len(t) / float(t.sum()),
                                 "model_ms": None if model is None else float(np.median(model)) * 1e3,
                                 "overhead_pct": None if model is None
                                 else float(np.median(t - model) / np.median(model)) * 100.0})
                    r = rows[-1]
                    extra = "" if model is None else f"  model {r['model_ms']:8.1f} ms  overhead {r['overhead_pct']:+.1f}%"
                    print(f"  {preset:5s} {route:14s} {transport:10s} p50 {r['p50_ms']:8.1f} ms  "
                          f"p99 {r['p99_ms']:8.1f} ms  {r['rps']:6.2f} req/s{extra}", flush=True)
    return rows


def print_table(rows: list[dict]) -> None:
    print("\n| preset | route | transport | p50 ms | p99 ms | req/s | server model p50 ms | overhead % of model |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        model = "—" if r["model_ms"] is None else f"{r['model_ms']:.1f}"
        over = "—" if r["overhead_pct"] is None else f"{r['overhead_pct']:+.1f}%"
        print(f"| {r['preset']} | {r['route']} | {r['transport']} | {r['p50_ms']:.1f} | {r['p99_ms']:.1f} | "
              f"{r['rps']:.2f} | {model} | {over} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", default="tiny,small")
    p.add_argument("--routes", default=",".join(ROUTES))
    p.add_argument("--requests", type=int, default=20, help="timed sequential requests per route and transport")
    p.add_argument("--views", type=int, default=2, help="views per instant in each request")
    args = p.parse_args(argv)
    torch.set_num_threads(1)  # the server runs with --threads 1 too: same compute for both
    rows = []
    for preset in args.presets.split(","):
        print(f"preset {preset}:", flush=True)
        rows += bench_preset(preset, requests=args.requests, views=args.views, routes=tuple(args.routes.split(",")))
    print_table(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
