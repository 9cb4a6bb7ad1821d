"""`n3dmap serve`: REST and gRPC inference over one model bundle, in one process."""

from __future__ import annotations

import argparse
import os

from services.cli.argtypes import (DEFAULT_FRAME_DT, FRAME_DT_HELP, frame_interval, non_negative_float, port,
                                   positive_float, positive_int)
from services.cli.egomotion_options import add_egomotion_arguments
from services.cli.moving_options import add_moving_object_arguments, moving_objects_config

# services.inference.codecs.MAX_REQUEST_PIXELS, written here so that `n3dmap --help` does not import the service
# (tests/unit/inference/test_pixel_budget.py checks they agree).
MAX_REQUEST_PIXELS = 64 * 2**20


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "serve", help="serve a model bundle over REST (FastAPI) and gRPC",
        description="Serve a model bundle over REST and gRPC in one process. SIGTERM drains in-flight "
                    "requests and stops; SIGHUP (or POST /v1/admin/reload) reloads the bundle.")
    p.add_argument("--bundle", required=True, help="model bundle directory (bundle.json + weights)")
    p.add_argument("--host", default="127.0.0.1", help="address both transports bind (default 127.0.0.1)")
    p.add_argument("--http-port", type=port, default=8000)
    p.add_argument("--grpc-port", type=port, default=50051)
    p.add_argument("--token", default=os.environ.get("N3DMAP_TOKEN"),
                   help="bearer token required by both transports (default: $N3DMAP_TOKEN; none = open)")
    p.add_argument("--tls-cert", help="PEM certificate for HTTPS and gRPC TLS (with --tls-key)")
    p.add_argument("--tls-key", help="PEM private key")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch intra-op threads (default: torch's)")
    p.add_argument("--max-batch", type=positive_int, default=8, help="largest micro-batch (default 8)")
    p.add_argument("--max-wait-ms", type=non_negative_float, default=2.0, help="longest wait to fill a batch (default 2)")
    p.add_argument("--queue", type=positive_int, default=64, help="waiting requests before 429 (default 64)")
    p.add_argument("--timeout", type=positive_float, default=30.0, help="per-request deadline in seconds (default 30)")
    p.add_argument("--frame-dt", type=frame_interval, default=DEFAULT_FRAME_DT, metavar="S", help=FRAME_DT_HELP)
    add_moving_object_arguments(p)  # the moving-objects route and both gRPC calls
    add_egomotion_arguments(p)
    p.add_argument("--max-body-mb", type=positive_float, default=64.0, help="largest request body in MiB (default 64)")
    p.add_argument("--max-request-pixels", type=positive_int, default=MAX_REQUEST_PIXELS, metavar="N",
                   help="most pixels one request may decode over all its images, rgb and depth each counted, "
                        f"on both transports (default {MAX_REQUEST_PIXELS} = 64 Mi: one instant of 16 full-HD "
                        "views, or a pair of 16-view instants at 1280×800); refused with 422 / INVALID_ARGUMENT "
                        "before it is decoded")
    p.add_argument("--drain", type=non_negative_float, default=10.0, help="seconds to drain in-flight requests on shutdown")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from services.cli.main import CliError
    from services.inference.runtime import RuntimeConfig
    from services.inference.server import ServeSettings, run as serve

    if bool(args.tls_cert) != bool(args.tls_key):
        raise CliError("--tls-cert and --tls-key go together")
    if args.http_port and args.http_port == args.grpc_port:
        raise CliError(f"--http-port and --grpc-port are both {args.http_port}; give two different ports")
    try:
        objects = moving_objects_config(args)
    except ValueError as e:
        raise CliError(str(e)) from None
    runtime = RuntimeConfig(bundle_dir=args.bundle, device=args.device, num_threads=args.threads,
                            max_batch=args.max_batch, max_wait_ms=args.max_wait_ms, max_queue=args.queue,
                            timeout_s=args.timeout, frame_dt=args.frame_dt, moving_objects=objects,
                            egomotion_fine=args.egomotion_fine, max_request_pixels=args.max_request_pixels)
    return serve(ServeSettings(runtime=runtime, host=args.host, http_port=args.http_port,
                               grpc_port=args.grpc_port, token=args.token or None, tls_cert=args.tls_cert,
                               tls_key=args.tls_key, max_body_bytes=int(args.max_body_mb * 2**20),
                               drain_s=args.drain, log_level=args.log_level))
