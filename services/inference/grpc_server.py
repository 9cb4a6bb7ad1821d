"""gRPC transport (grpc.aio) over the inference runtime: n3dmap.v1.Inference + health + reflection.

Status codes: INVALID_ARGUMENT (bad field, named in the message), UNIMPLEMENTED (module absent from
the bundle), RESOURCE_EXHAUSTED (queue full), DEADLINE_EXCEEDED, UNAVAILABLE (not ready),
UNAUTHENTICATED (bearer token). The server binds with SO_REUSEPORT off, so a taken port fails loudly.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import time

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from core.errors import DataError, ShapeError
from n3dmap.v1 import inference_pb2, inference_pb2_grpc
from services.inference import codecs, wire
from services.inference.errors import InvalidInput, ModuleUnavailable, NotReady, Overloaded, RequestTimeout
from services.inference.camera_state import CameraState
from services.inference.camera_stream import MovingStream
from services.inference.routes import DetectInput, MapInput, flow_input, moving_input, pair_input
from services.inference.stream_options import stream_options
from services.inference.runtime import Runtime
from services.inference.validation import check_min_score

log = logging.getLogger("n3dmap.grpc")

SERVICE_NAME = inference_pb2.DESCRIPTOR.services_by_name["Inference"].full_name
# FlowRequest.stabilise -> core.pipeline.stabilise mode; UNSPECIFIED keeps the poses, as before the field.
STABILISE = {inference_pb2.STABILISE_UNSPECIFIED: "poses", inference_pb2.STABILISE_POSES: "poses",
             inference_pb2.STABILISE_EGOMOTION: "egomotion", inference_pb2.STABILISE_NONE: "none"}
MAX_MESSAGE_BYTES = 64 * 2**20
# Cameras one StreamMovingObjects call may carry: each keeps its previous frame and that frame's encoding (several
# MB) for the call's life, so ids that keep changing would grow the server's memory without bound.
MAX_STREAM_CAMERAS = 64
_CODES = [(InvalidInput, grpc.StatusCode.INVALID_ARGUMENT), (ModuleUnavailable, grpc.StatusCode.UNIMPLEMENTED),
          (Overloaded, grpc.StatusCode.RESOURCE_EXHAUSTED), (RequestTimeout, grpc.StatusCode.DEADLINE_EXCEEDED),
          (NotReady, grpc.StatusCode.UNAVAILABLE), (ShapeError, grpc.StatusCode.INVALID_ARGUMENT),
          (DataError, grpc.StatusCode.INVALID_ARGUMENT)]


def channel_options(max_bytes: int = MAX_MESSAGE_BYTES) -> list[tuple[str, int]]:
    """Message size limits for both ends (gRPC's default receive limit is 4 MB)."""
    return [("grpc.max_receive_message_length", max_bytes), ("grpc.max_send_message_length", max_bytes)]


def _code_of(e: Exception) -> grpc.StatusCode | None:
    for cls, code in _CODES:
        if isinstance(e, cls):
            return code
    return None


def _failure(rpc: str, e: Exception) -> tuple[grpc.StatusCode, str]:
    """The status a failed call ends with: the typed errors' own, INTERNAL (logged) for anything else."""
    code = _code_of(e)
    if code is not None:
        return code, str(e)
    log.exception("%s failed", rpc)
    return grpc.StatusCode.INTERNAL, f"{type(e).__name__}: {e}"


def _deadline(context: grpc.aio.ServicerContext) -> float | None:
    """Seconds left of the call's deadline (None: the call has none, the runtime's --timeout applies). A deadline
    already passed is 0, which times the request out at once (DEADLINE_EXCEEDED) instead of granting it the
    runtime's full default (it was None, i.e. 30 s, for a caller that had already given up)."""
    remaining = context.time_remaining()
    return None if remaining is None else max(remaining, 0.0)


class InferenceServicer(inference_pb2_grpc.InferenceServicer):
    def __init__(self, runtime: Runtime):
        self.runtime = runtime

    async def _call(self, rpc: str, context, fn):
        started = time.perf_counter()
        status = "OK"
        try:
            return await fn()
        except (grpc.aio.AbortError, grpc.RpcError):
            raise
        except asyncio.CancelledError:   # the client cancelled or its deadline passed: not an OK call
            status = "CANCELLED"
            raise
        except Exception as e:
            code, message = _failure(rpc, e)
            status = code.name
            await context.abort(code, message)
        finally:
            self.runtime.metrics.observe_request("grpc", rpc, status, time.perf_counter() - started)

    def _grid(self) -> inference_pb2.Grid:
        return wire.grid_proto(self.runtime.bundle.preset.grid.to_dict())

    async def Map(self, request: inference_pb2.MapRequest, context):
        async def run():
            item = MapInput(views=await wire.off_loop(wire.views_from_proto, request.views, "views", self._budget()),
                            features=request.features)
            answer = await self.runtime.infer("map", item, timeout_s=_deadline(context))
            arrays = {k: codecs.numpy_to_tensor(v) for k, v in wire.map_arrays(answer.result).items()}
            return inference_pb2.MapResponse(info=wire.info_proto(answer), grid=self._grid(), **arrays)
        return await self._call("Map", context, run)

    def _budget(self) -> codecs.PixelBudget:
        """A fresh request's pixel budget (`serve --max-request-pixels`)."""
        return codecs.PixelBudget(self.runtime.config.max_request_pixels)

    async def _views(self, request) -> tuple:
        """The pair's two instants, decoded off the event loop (wire.off_loop says why)."""
        def decode():
            budget = self._budget()   # one request: both instants draw on it
            return (wire.views_from_proto(request.views0, "views0", budget),
                    wire.views_from_proto(request.views1, "views1", budget))
        return await wire.off_loop(decode)

    async def Egomotion(self, request: inference_pb2.PairRequest, context):
        async def run():
            answer = await self.runtime.infer("egomotion", pair_input(*await self._views(request)),
                                              timeout_s=_deadline(context))
            return inference_pb2.EgomotionResponse(info=wire.info_proto(answer),
                                                   cam0_T_cam1=codecs.numpy_to_tensor(answer.result.cam0_T_cam1))
        return await self._call("Egomotion", context, run)

    async def Flow(self, request: inference_pb2.FlowRequest, context):
        async def run():
            stabilise = STABILISE.get(request.stabilise, f"enum value {request.stabilise}")
            answer = await self.runtime.infer("flow", flow_input(*await self._views(request), stabilise),
                                              timeout_s=_deadline(context))
            return inference_pb2.FlowResponse(info=wire.info_proto(answer), grid=self._grid(),
                                              flow=codecs.numpy_to_tensor(answer.result.flow))
        return await self._call("Flow", context, run)

    async def Detect(self, request: inference_pb2.DetectRequest, context):
        async def run():
            views = await wire.off_loop(wire.views_from_proto, request.views, "views", self._budget())
            item = DetectInput(views=views, min_score=check_min_score(request.min_score))
            answer = await self.runtime.infer("detect", item, timeout_s=_deadline(context))
            return inference_pb2.DetectionsResponse(info=wire.info_proto(answer), detections=wire.detections_proto(
                answer.result, frame=answer.frame, bundle_version=answer.bundle_version, views=views))
        return await self._call("Detect", context, run)

    async def MovingObjects(self, request: inference_pb2.MovingObjectsRequest, context):
        async def run():
            views0, views1 = await self._views(request)
            score = check_min_score(request.min_score, low=-1.0) if request.HasField("min_score") else -1.0
            item = moving_input(views0, views1, min_score=score, frame_dt=self.runtime.config.frame_dt,
                                modules=self.runtime.modules, config=self.runtime.config.moving_objects)
            answer = await self.runtime.infer("moving_objects", item, timeout_s=_deadline(context))
            return inference_pb2.DetectionsResponse(info=wire.info_proto(answer), detections=wire.detections_proto(
                answer.result, frame=answer.frame, bundle_version=answer.bundle_version, views=views1,
                ref_views=views0))
        return await self._call("MovingObjects", context, run)

    async def Models(self, request, context):
        async def run():
            d = self.runtime.describe()
            return inference_pb2.ModelsResponse(
                bundle_version=d["bundle_version"], preset=d["preset"], modules=d["modules"], routes=d["routes"],
                grid=wire.grid_proto(d["grid"]), device=d["device"], meta_json=d["meta_json"])
        return await self._call("Models", context, run)

    async def StreamMovingObjects(self, request_iterator, context):
        """Per camera, moving objects between its previous frame and this one: the zenoh bridge's step
        (services.inference.camera_stream), run on the model thread; the call's metadata may ask for the
        bridge's levelled placement (services.inference.stream_options)."""
        started = time.perf_counter()
        status = "OK"
        try:
            self.runtime.require("moving_objects")
            stream = MovingStream(self.runtime, min_score=-1.0, frame_dt=self.runtime.config.frame_dt,
                                  objects=self.runtime.config.moving_objects,
                                  **stream_options(context.invocation_metadata()))
            states: dict[str, CameraState] = {}
            async for frame in request_iterator:
                received = time.perf_counter()
                view = await wire.off_loop(wire.view_from_proto, frame, "frame", self._budget())
                if frame.camera_id not in states and len(states) >= MAX_STREAM_CAMERAS:
                    # each camera keeps its previous frame and encoding for the call's life (several MB)
                    raise Overloaded(f"frame.camera_id: one call streams at most {MAX_STREAM_CAMERAS} cameras; "
                                     "open another call for more")
                state = states.setdefault(frame.camera_id, CameraState())
                kind = state.verdict(view.sequence)
                if kind is not None:
                    # a duplicate or out-of-order frame: dropped unanswered, as the bridge drops it, and counted
                    self.runtime.metrics.stream_dropped.labels(kind).inc()
                    continue
                answer = await self.runtime.call_on_model_thread(
                    lambda: stream.step(frame.camera_id, state, view), timeout_s=_deadline(context))
                state.advance(view)
                answer.detections.latency_s = time.perf_counter() - received
                yield answer.detections
        except (grpc.aio.AbortError, grpc.RpcError):
            raise
        except asyncio.CancelledError:   # the client cancelled or its deadline passed: not an OK call
            status = "CANCELLED"
            raise
        except Exception as e:
            code, message = _failure("StreamMovingObjects", e)
            status = code.name
            await context.abort(code, message)
        finally:
            self.runtime.metrics.observe_request("grpc", "StreamMovingObjects", status, time.perf_counter() - started)


class _TokenInterceptor(grpc.aio.ServerInterceptor):
    """Rejects calls without `authorization: Bearer <token>` (health checks stay open for probes)."""

    def __init__(self, token: str):
        self._want = f"Bearer {token}".encode()

        async def deny(request, context):
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")

        async def deny_stream(request_iterator, context):
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")
            yield  # pragma: no cover (makes this an async generator)

        self._deny_unary = grpc.unary_unary_rpc_method_handler(deny)
        self._deny_stream = grpc.stream_stream_rpc_method_handler(deny_stream)

    async def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method
        if method.startswith("/grpc.health.v1.Health/"):
            return await continuation(handler_call_details)
        got = dict(handler_call_details.invocation_metadata or ()).get("authorization", "")
        if hmac.compare_digest(str(got).encode(), self._want):
            return await continuation(handler_call_details)
        return self._deny_stream if method.endswith("/StreamMovingObjects") else self._deny_unary


async def start_grpc_server(runtime: Runtime, *, host: str, port: int, token: str | None = None,
                            tls_cert: bytes | None = None, tls_key: bytes | None = None
                            ) -> tuple[grpc.aio.Server, int, health.aio.HealthServicer]:
    """Build, bind and start the server. Returns (server, bound port, health servicer)."""
    interceptors = [_TokenInterceptor(token)] if token else []
    server = grpc.aio.server(interceptors=interceptors,
                             options=channel_options() + [("grpc.so_reuseport", 0)])
    inference_pb2_grpc.add_InferenceServicer_to_server(InferenceServicer(runtime), server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection((SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), server)
    address = f"{host}:{port}"
    try:
        if tls_cert is not None:
            bound = server.add_secure_port(address, grpc.ssl_server_credentials([(tls_key, tls_cert)]))
        else:
            bound = server.add_insecure_port(address)
    except RuntimeError as e:  # grpcio raises when the port is taken (SO_REUSEPORT is off)
        raise OSError(f"gRPC could not bind {address}: is the port taken? ({e})") from None
    if bound == 0:
        raise OSError(f"gRPC could not bind {address} (port taken?)")
    await server.start()
    for name in ("", SERVICE_NAME):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    return server, bound, health_servicer
