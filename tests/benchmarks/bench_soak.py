"""Soak benchmark of the inference service: OpenAPI fuzzing, then sustained mixed REST + gRPC load, on one
real `n3dmap serve` process over a tiny bundle.

    python tests/benchmarks/bench_soak.py [--cases 1000] [--clients 64] [--seconds 60] [--warmup 10]

1. **Fuzzing.** schemathesis (its CLI, `st run`, against the server's /openapi.json, check
   `not_a_server_error`) runs the examples, coverage and fuzzing phases, again with fresh seeds (fuzzing
   only) until at least `--cases` test cases were sent. Every request/response is read back from the run's
   HAR report and counted by status class; any 5xx fails the benchmark and is printed with its request.
2. **Load.** `--clients` concurrent clients, alternately REST (the OpenAPI request examples the service
   publishes, POSTed as JSON) and gRPC (the same views as protobuf), each cycling through map, egomotion,
   flow, detect and moving objects for `--seconds`, back to back; a rejected client waits as a 429's
   Retry-After says (1 s after a RESOURCE_EXHAUSTED). Only 2xx / 429 (REST) and OK / RESOURCE_EXHAUSTED
   (gRPC) are allowed; anything else (including a client-side timeout or connection error) fails. The
   server's RSS (VmRSS of its PID) is sampled every 0.5 s: its median over the window right after
   `--warmup` and over the window at the end (each a third of the measured span, at most 10 s; RSS
   swings by tens of MiB with the batches in flight) may grow by less than `--max-rss-growth` %
   (default 5). The point values at warm-up and at the end, and the peak, are printed too.

Prints the figures (cases and status classes; per transport counts, p50/p99 latency, throughput over
the measured window; RSS at warm-up, end, peak and growth; the load average) and one JSON line prefixed
`SOAK_JSON `. Exit status 0 when every check holds, 1 otherwise. The server is stopped by its PID at the
end, also on error.
"""

from __future__ import annotations

import argparse
import asyncio
import glob
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from tests.integration.serve_support import ServerProcess, make_bundle  # noqa: E402

# REST path <-> gRPC method of each inference route the load mixes.
ROUTES = {"/v1/map": "Map", "/v1/egomotion": "Egomotion", "/v1/flow": "Flow", "/v1/detect": "Detect",
          "/v1/moving-objects": "MovingObjects"}
REST_OK = lambda status: 200 <= status < 300 or status == 429  # noqa: E731
GRPC_OK = ("OK", "RESOURCE_EXHAUSTED")
RSS_EVERY_S = 0.5   # server RSS sampling period
RSS_WINDOW_S = 10.0  # longest window whose median RSS is compared (after warm-up vs at the end)
BACKOFF_S = 1.0  # a rejected client's wait: the REST 429's Retry-After (the server says 1 s), this for gRPC


# ----------------------------------------------------------------------------------- server


def rss_bytes(pid: int) -> int:
    """Resident set size of `pid` (VmRSS from /proc/PID/status)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


# ----------------------------------------------------------------------------------- fuzzing


def _har_entries(report_dir: Path) -> list[dict]:
    entries = []
    for path in sorted(glob.glob(str(report_dir / "*.json"))):
        entries += json.loads(Path(path).read_text())["log"]["entries"]
    return entries


def _describe(entry: dict) -> str:
    req, resp = entry["request"], entry["response"]
    body = (req.get("postData") or {}).get("text", "")
    return (f"{req['method']} {req['url']} -> {resp['status']}\n    request body: {body[:400]!r}\n"
            f"    response: {(resp.get('content') or {}).get('text', '')[:400]!r}")


def run_schemathesis(url: str, *, cases: int, phases: str, seed: int, workdir: Path, workers: int = 1,
                     max_rounds: int = 20) -> dict:
    """st run rounds against `url` until ≥ `cases` cases were sent. The first round runs `phases`, later ones
    fuzzing only, each with its own seed. -> counts and the 5xx requests."""
    operations = len([1 for ops in _openapi(url)["paths"].values() for _ in ops])
    status: Counter = Counter()
    server_errors: list[str] = []
    failed_runs: list[str] = []
    sent, rounds, started = 0, 0, time.perf_counter()
    while sent < cases and rounds < max_rounds:
        remaining = cases - sent
        per_op = max(1, math.ceil(remaining / operations))
        round_phases = phases if rounds == 0 else "fuzzing"
        report_dir = workdir / f"st-{rounds}"
        cmd = [sys.executable, "-m", "schemathesis.cli", "run", url + "/openapi.json",
               "--checks", "not_a_server_error", "--phases", round_phases, "--max-examples", str(per_op),
               "--seed", str(seed + rounds), "--workers", str(workers), "--request-timeout", "60",
               "--report", "har", "--report-dir", str(report_dir), "--no-color"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600,
                              env={**os.environ, "SCHEMATHESIS_TELEMETRY": "false"})
        entries = _har_entries(report_dir)
        for e in entries:
            code = e["response"]["status"]
            status[f"{code // 100}xx" if code else "no response"] += 1
            if code >= 500 or code == 0:
                server_errors.append(_describe(e))
        if proc.returncode != 0:
            failed_runs.append(f"st run (phases {round_phases}, seed {seed + rounds}) exited {proc.returncode}:\n"
                               + proc.stdout[-3000:] + proc.stderr[-1500:])
        print(f"  schemathesis round {rounds + 1} ({round_phases}, seed {seed + rounds}, ≤{per_op}/operation): "
              f"{len(entries)} cases, exit {proc.returncode}", flush=True)
        sent += len(entries)
        rounds += 1
        if not entries:
            break  # nothing was sent: looping would not help
    return {"cases": sent, "rounds": rounds, "operations": operations, "by_class": dict(sorted(status.items())),
            "server_errors": server_errors, "failed_runs": failed_runs,
            "seconds": time.perf_counter() - started}


def _openapi(url: str) -> dict:
    import httpx

    return httpx.get(url + "/openapi.json", timeout=30).json()


# ----------------------------------------------------------------------------------- load


def request_examples(spec: dict) -> dict[str, dict]:
    """{REST path: the first OpenAPI JSON request example} of each inference route."""
    out = {}
    for path in ROUTES:
        media = spec["paths"][path]["post"]["requestBody"]["content"]["application/json"]
        out[path] = next(iter(media["examples"].values()))["value"]
    return out


def grpc_requests(examples: dict[str, dict]) -> dict[str, object]:
    """The same requests as protobuf messages: {gRPC method: request}."""
    from n3dmap.v1 import inference_pb2
    from services.inference import schemas, wire
    from services.inference.client import Frames, frame_proto

    def frames(views_json: list) -> list:
        views = wire.views_from_json(schemas.MapRequestJSON(views=views_json).views, "views")
        f = Frames(rgb=views.rgb, depth=views.depth, pix_T_cam=views.pix_T_cam, world_T_cam=views.world_T_cam,
                   camera_id=views.camera_ids[0] if views.camera_ids else "", sequence=views.sequence,
                   timestamp=views.timestamp, capture_time=views.capture_time)
        return [frame_proto(f, v) for v in range(views.rgb.shape[0])]

    m, p = examples["/v1/map"], examples["/v1/egomotion"]
    v0, v1 = frames(p["views0"]), frames(p["views1"])
    return {
        "Map": inference_pb2.MapRequest(views=frames(m["views"]), features=bool(m.get("features", False))),
        "Egomotion": inference_pb2.PairRequest(views0=v0, views1=v1),
        "Flow": inference_pb2.FlowRequest(views0=v0, views1=v1, stabilise=inference_pb2.STABILISE_POSES),
        "Detect": inference_pb2.DetectRequest(views=frames(examples["/v1/detect"]["views"]),
                                              min_score=examples["/v1/detect"].get("min_score", 0.0)),
        "MovingObjects": inference_pb2.MovingObjectsRequest(
            views0=v0, views1=v1, min_score=examples["/v1/moving-objects"].get("min_score", -1.0)),
    }


async def _load(server: ServerProcess, *, clients: int, seconds: float, warmup: float, timeout_s: float) -> dict:
    import grpc
    import httpx

    from n3dmap.v1 import inference_pb2_grpc
    from services.inference.grpc_server import channel_options

    spec = _openapi(server.url)
    examples = request_examples(spec)
    bodies = {path: json.dumps(body).encode() for path, body in examples.items()}
    protos = grpc_requests(examples)
    paths = list(ROUTES)

    records: list[tuple[float, str, str, str, float]] = []   # (end time, transport, route, status, latency s)
    failures: list[str] = []
    t0 = time.perf_counter()
    stop_at = t0 + seconds

    async def rest_client(i: int) -> None:
        async with httpx.AsyncClient(base_url=server.url, timeout=timeout_s) as http:
            k = i
            while time.perf_counter() < stop_at:
                path = paths[k % len(paths)]
                k += 1
                started = time.perf_counter()
                retry_after = None
                try:
                    r = await http.post(path, content=bodies[path], headers={"content-type": "application/json"})
                    status = str(r.status_code)
                    if r.status_code == 429:
                        retry_after = float(r.headers.get("retry-after", BACKOFF_S))
                    elif not REST_OK(r.status_code) and len(failures) < 20:
                        failures.append(f"REST {path} -> {r.status_code}: {r.text[:300]}")
                except httpx.HTTPError as e:
                    status = type(e).__name__
                    if len(failures) < 20:
                        failures.append(f"REST {path} -> {status}: {e}")
                now = time.perf_counter()
                records.append((now - t0, "REST", path, status, now - started))
                if retry_after is not None:  # as a well-behaved client: wait as the server asks
                    await asyncio.sleep(min(retry_after, max(stop_at - now, 0.0)))

    async def grpc_client(i: int) -> None:
        async with grpc.aio.insecure_channel(server.target, options=channel_options()) as channel:
            stub = inference_pb2_grpc.InferenceStub(channel)
            k = i
            while time.perf_counter() < stop_at:
                method = list(ROUTES.values())[k % len(ROUTES)]
                k += 1
                started = time.perf_counter()
                try:
                    await getattr(stub, method)(protos[method], timeout=timeout_s)
                    status = "OK"
                except grpc.aio.AioRpcError as e:
                    status = e.code().name
                    if status not in GRPC_OK and len(failures) < 20:
                        failures.append(f"gRPC {method} -> {status}: {e.details()}")
                now = time.perf_counter()
                records.append((now - t0, "gRPC", method, status, now - started))
                if status == "RESOURCE_EXHAUSTED":  # gRPC has no Retry-After: back off as REST clients do
                    await asyncio.sleep(min(BACKOFF_S, max(stop_at - now, 0.0)))

    rss: list[tuple[float, int]] = []

    async def sample_rss() -> None:
        while time.perf_counter() < stop_at:
            rss.append((time.perf_counter() - t0, rss_bytes(server.proc.pid)))
            await asyncio.sleep(RSS_EVERY_S)

    load_before = os.getloadavg()
    rss_start = rss_bytes(server.proc.pid)
    sampler = asyncio.create_task(sample_rss())
    warm = {}

    async def note_warm() -> None:
        await asyncio.sleep(warmup)
        warm["rss"], warm["t"] = rss_bytes(server.proc.pid), time.perf_counter() - t0
        rss.append((warm["t"], warm["rss"]))

    warm_task = asyncio.create_task(note_warm())
    await asyncio.gather(*(rest_client(i) if i % 2 == 0 else grpc_client(i) for i in range(clients)))
    await warm_task
    sampler.cancel()
    elapsed = time.perf_counter() - t0
    rss_end = rss_bytes(server.proc.pid)
    rss.append((elapsed, rss_end))
    load_after = os.getloadavg()
    return {"records": records, "failures": failures, "rss": rss, "rss_start": rss_start, "rss_warm": warm["rss"],
            "warm_t": warm["t"], "rss_end": rss_end, "elapsed": elapsed, "load_before": load_before,
            "load_after": load_after}


def summarise_load(raw: dict, *, clients: int, warmup: float) -> dict:
    records = raw["records"]
    status = Counter(f"{transport} {s}" for _, transport, _, s, _ in records)
    bad = {k: n for k, n in status.items()
           if not ((k.startswith("REST ") and k[5:].isdigit() and REST_OK(int(k[5:])))
                   or (k.startswith("gRPC ") and k[5:] in GRPC_OK))}
    window = [r for r in records if r[0] >= raw["warm_t"]]
    span = max(raw["elapsed"] - raw["warm_t"], 1e-9)
    per_transport = {}
    for transport in ("REST", "gRPC", "all"):
        rows = [r for r in window if transport in ("all", r[1])]
        ok = [r[4] for r in rows if r[3] in ("200", "OK")]
        per_transport[transport] = {
            "requests": len(rows), "ok": len(ok),
            "rejected_429": sum(1 for r in rows if r[3] in ("429", "RESOURCE_EXHAUSTED")),
            "p50_ms": float(np.percentile(ok, 50)) * 1e3 if ok else None,
            "p99_ms": float(np.percentile(ok, 99)) * 1e3 if ok else None,
            "ok_per_s": len(ok) / span}
    # RSS swings by tens of MiB with the batches in flight, so growth compares medians over a window right
    # after the warm-up and one at the end (a third of the measured span, at most RSS_WINDOW_S each).
    w = min(RSS_WINDOW_S, (raw["elapsed"] - raw["warm_t"]) / 3)
    base = float(np.median([b for t, b in raw["rss"] if raw["warm_t"] <= t <= raw["warm_t"] + w]))
    tail = float(np.median([b for t, b in raw["rss"] if t >= raw["elapsed"] - w]))
    growth = (tail - base) / base * 100.0
    return {"clients": clients, "seconds": raw["elapsed"], "warmup_s": raw["warm_t"], "total_requests": len(records),
            "status": dict(sorted(status.items())), "disallowed": bad, "window": per_transport,
            "rss_mb": {"start": raw["rss_start"] / 2**20, "after_warmup": raw["rss_warm"] / 2**20,
                       "end": raw["rss_end"] / 2**20, "peak": max(b for _, b in raw["rss"]) / 2**20,
                       "median_after_warmup": base / 2**20, "median_end": tail / 2**20},
            "rss_window_s": w, "rss_samples": len(raw["rss"]), "rss_growth_pct": growth,
            "rss_series_mb": _series(raw["rss"], raw["elapsed"]),
            "rss_growth_point_pct": (raw["rss_end"] - raw["rss_warm"]) / raw["rss_warm"] * 100.0, "loadavg_before": raw["load_before"], "loadavg_after": raw["load_after"],
            "failures": raw["failures"]}


def _series(rss: list[tuple[float, int]], elapsed: float, step_s: float = 5.0) -> list[list[float]]:
    """[[t s, median RSS MiB]] per `step_s` slice of the load: how RSS evolved."""
    out = []
    for start in np.arange(0.0, elapsed, step_s):
        chunk = [b for t, b in rss if start <= t < start + step_s]
        if chunk:
            out.append([round(float(start + step_s / 2), 1), round(float(np.median(chunk)) / 2**20, 1)])
    return out


# ----------------------------------------------------------------------------------- main


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", type=int, default=1000, help="schemathesis test cases to send at least (0: skip)")
    p.add_argument("--phases", default="examples,coverage,fuzzing", help="schemathesis phases of the first round")
    p.add_argument("--seed", type=int, default=1, help="schemathesis seed of the first round (later rounds +1 each)")
    p.add_argument("--clients", type=int, default=64, help="concurrent load clients, alternately REST and gRPC")
    p.add_argument("--seconds", type=float, default=60.0, help="load duration (0: skip the load)")
    p.add_argument("--warmup", type=float, default=10.0, help="seconds of load before the RSS baseline")
    p.add_argument("--max-rss-growth", type=float, default=5.0, help="allowed RSS growth after warm-up, %%")
    p.add_argument("--client-timeout", type=float, default=60.0,
                   help="client-side deadline per load request, s (above the server's own, 30 s)")
    p.add_argument("--preset", default="tiny", help="preset of the freshly initialised bundle served")
    p.add_argument("--server-arg", action="append", default=[],
                   help="extra `n3dmap serve` argument (repeatable), e.g. --server-arg=--queue=32")
    p.add_argument("--keep", metavar="DIR", help="write the bundle, server log and reports here (default: a temp dir)")
    args = p.parse_args(argv)
    if args.seconds and not 0 <= args.warmup < args.seconds:
        p.error("--warmup must lie in [0, --seconds)")

    tmp = None if args.keep else tempfile.TemporaryDirectory(prefix="bench-soak-")
    work = Path(args.keep or tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    ok, summary = True, {"cpus": os.cpu_count()}
    try:
        bundle = make_bundle(work / "bundle", preset_name=args.preset, note="bench_soak")
        server = ServerProcess(bundle, *args.server_arg, log_path=work / "server.log")
        with server:
            print(f"server pid {server.proc.pid}: REST {server.url}  gRPC {server.target}  "
                  f"(bundle {args.preset}, {os.cpu_count()} CPUs, load average {_load_str(os.getloadavg())})",
                  flush=True)
            if args.cases > 0:
                print(f"fuzzing: schemathesis, at least {args.cases} cases", flush=True)
                fz = run_schemathesis(server.url, cases=args.cases, phases=args.phases, seed=args.seed, workdir=work)
                summary["fuzz"] = {k: v for k, v in fz.items() if k not in ("server_errors", "failed_runs")}
                summary["fuzz"]["server_errors"] = len(fz["server_errors"])
                print(f"  {fz['cases']} cases over {fz['operations']} operations in {fz['rounds']} round(s), "
                      f"{fz['seconds']:.1f} s; responses by class: "
                      + ", ".join(f"{k} {n}" for k, n in fz["by_class"].items()), flush=True)
                if fz["server_errors"]:
                    ok = False
                    print(f"  FAIL: {len(fz['server_errors'])} server errors:", flush=True)
                    for e in fz["server_errors"][:20]:
                        print("  " + e, flush=True)
                if fz["failed_runs"]:
                    ok = False
                    for f in fz["failed_runs"]:
                        print("  FAIL: " + f, flush=True)
                if fz["cases"] < args.cases:
                    ok = False
                    print(f"  FAIL: only {fz['cases']} of {args.cases} cases were sent", flush=True)
            if args.seconds > 0:
                print(f"load: {args.clients} clients (REST {(args.clients + 1) // 2}, gRPC {args.clients // 2}) "
                      f"for {args.seconds:g} s, RSS baseline after {args.warmup:g} s", flush=True)
                raw = asyncio.run(_load(server, clients=args.clients, seconds=args.seconds, warmup=args.warmup,
                                        timeout_s=args.client_timeout))
                ld = summarise_load(raw, clients=args.clients, warmup=args.warmup)
                summary["load"] = {k: v for k, v in ld.items() if k != "failures"}
                _print_load(ld)
                if ld["disallowed"]:
                    ok = False
                    print(f"  FAIL: disallowed outcomes {ld['disallowed']}", flush=True)
                    for f in ld["failures"]:
                        print("    " + f, flush=True)
                if not ld["window"]["all"]["ok"]:
                    ok = False
                    print("  FAIL: no request succeeded after the warm-up", flush=True)
                if ld["rss_growth_pct"] >= args.max_rss_growth:
                    ok = False
                    print(f"  FAIL: RSS grew {ld['rss_growth_pct']:.2f}% after warm-up "
                          f"(limit {args.max_rss_growth:g}%)", flush=True)
            status = server.stop()
            summary["server_exit"] = status
            if status != 0:
                ok = False
                print(f"  FAIL: server exited {status}; log tail:\n{server.read_log()[-2000:]}", flush=True)
    finally:
        summary["loadavg_end"] = os.getloadavg()
        if tmp is not None:
            tmp.cleanup()
    summary["ok"] = ok
    print(f"load average at the end: {_load_str(summary['loadavg_end'])}; {'PASS' if ok else 'FAIL'}", flush=True)
    print("SOAK_JSON " + json.dumps(summary, default=float), flush=True)
    return 0 if ok else 1


def _load_str(load) -> str:
    return " ".join(f"{x:.2f}" for x in load)


def _print_load(ld: dict) -> None:
    print(f"  {ld['total_requests']} requests in {ld['seconds']:.1f} s; outcomes: "
          + ", ".join(f"{k} {n}" for k, n in ld["status"].items()), flush=True)
    print(f"  after warm-up ({ld['seconds'] - ld['warmup_s']:.1f} s window):", flush=True)
    for transport, w in ld["window"].items():
        lat = "—" if w["p50_ms"] is None else f"p50 {w['p50_ms']:.0f} ms  p99 {w['p99_ms']:.0f} ms"
        print(f"    {transport:5s} {w['requests']:6d} requests  {w['ok']:6d} ok  {w['rejected_429']:5d} 429  "
              f"{lat}  {w['ok_per_s']:.1f} ok/s", flush=True)
    r = ld["rss_mb"]
    print(f"  server RSS: start {r['start']:.1f} MiB, after warm-up {r['after_warmup']:.1f} MiB, end {r['end']:.1f} "
          f"MiB ({ld['rss_growth_point_pct']:+.2f}%), peak {r['peak']:.1f} MiB", flush=True)
    print(f"  server RSS medians over {ld['rss_window_s']:.1f} s windows: after warm-up {r['median_after_warmup']:.1f} "
          f"MiB, at the end {r['median_end']:.1f} MiB; growth after warm-up {ld['rss_growth_pct']:+.2f}% "
          f"({ld['rss_samples']} samples)", flush=True)
    print("  server RSS MiB by 5 s: " + " ".join(f"{mb:.0f}" for _, mb in ld["rss_series_mb"]), flush=True)
    print(f"  load average before {_load_str(ld['loadavg_before'])}, after {_load_str(ld['loadavg_after'])}",
          flush=True)


if __name__ == "__main__":
    sys.exit(main())
