"""REST transport (FastAPI) over the inference runtime.

Routes: POST /v1/map, /v1/egomotion, /v1/flow, /v1/detect, /v1/moving-objects (JSON, or a binary
`.npz` body with Content-Type application/x-npz or application/octet-stream and options as query
parameters), GET /v1/models, POST /v1/admin/reload, GET /healthz, /readyz, /metrics.
Map and flow answer `.npz` instead of JSON when the request says `Accept: application/x-npz`.

Errors are JSON `{error, detail, field}`: 422 invalid input (naming the field), 404 module absent
from the bundle, 413 body too large, 429 overloaded, 504 timeout, 503 not ready, 401 bad token, 500 a fault of the server
(`internal`; the traceback goes to the server's log).
The optional bearer token guards every /v1 route; probes and /metrics stay open.
"""

from __future__ import annotations

import hmac
import json
import logging
import time
from contextlib import asynccontextmanager
from typing import Annotated, Any, Callable

import numpy as np
from fastapi import Body, Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ValidationError

from core.errors import BundleError, DataError, ShapeError
from services.inference import codecs, examples, schemas, wire
from services.inference.errors import (InvalidInput, ModuleUnavailable, NotReady, Overloaded,
                                       RequestTimeout, ServiceError)
from services.inference.routes import DetectInput, MapInput, flow_input, moving_input, pair_input
from services.inference.runtime import Answer, Runtime
from services.inference.validation import check_min_score

log = logging.getLogger("n3dmap.rest")

NPZ = "application/x-npz"
BINARY_TYPES = (NPZ, "application/octet-stream")
DEFAULT_MAX_BODY = 64 * 2**20

_STATUS: list[tuple[type, int, str]] = [
    (InvalidInput, 422, "invalid_input"), (ModuleUnavailable, 404, "module_unavailable"),
    (Overloaded, 429, "overloaded"), (RequestTimeout, 504, "timeout"), (NotReady, 503, "not_ready"),
]


def error_response(status: int, error: str, detail: str, field: str | None = None, headers=None) -> JSONResponse:
    return JSONResponse({"error": error, "detail": detail, "field": field}, status_code=status, headers=headers)


def _service_error(e: Exception) -> JSONResponse:
    for cls, status, name in _STATUS:
        if isinstance(e, cls):
            headers = {"Retry-After": "1"} if status in (429, 503) else None
            return error_response(status, name, str(e), getattr(e, "field", None), headers)
    if isinstance(e, (ShapeError, DataError)):  # the model refused validated input (e.g. unsupported size)
        return error_response(422, "invalid_input", str(e), "views")
    return error_response(500, "internal", f"{type(e).__name__}: {e}")


def _request_body_schema(model: type[BaseModel], npz_doc: str, json_examples: dict) -> dict:
    """OpenAPI requestBody naming both encodings: JSON (the model, with request examples that Swagger's
    "Try it out" sends as they are) or a binary .npz."""
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": f"#/components/schemas/{model.__name__}"},
                             "examples": json_examples},
        NPZ: {"schema": {"type": "string", "format": "binary"}, "description": npz_doc},
    }}}


def create_app(runtime: Runtime, *, token: str | None = None, max_body_bytes: int = DEFAULT_MAX_BODY,
               lifespan: Callable | None = None) -> FastAPI:
    """The FastAPI app over `runtime`. `lifespan` (an async context manager factory taking the app)
    defaults to starting and stopping the runtime; server.py passes one that also runs gRPC."""

    @asynccontextmanager
    async def default_lifespan(app: FastAPI):
        await runtime.start()
        yield
        await runtime.stop()

    app = FastAPI(
        title="n3dmap inference", version="1",
        description="3D feature maps, occupancy, egomotion, 3D flow, 3D detection and moving objects "
                    "from RGB-D frames. Poses are 4×4 `a_T_b` (OpenCV cameras, metres); every volume, "
                    "pose and box of a response is in `ref`, the camera of the first view.",
        lifespan=lifespan or default_lifespan, max_body_size=max_body_bytes)
    app.state.runtime = runtime
    # Component schemas referenced by the hand-written request bodies below.
    extra_models = (schemas.MapRequestJSON, schemas.PairRequestJSON, schemas.FlowRequestJSON,
                    schemas.DetectRequestJSON, schemas.MovingObjectsRequestJSON)

    def check_token(request: Request) -> None:
        if token is None:
            return
        got = request.headers.get("authorization", "")
        if not hmac.compare_digest(got.encode(), f"Bearer {token}".encode()):
            raise _Unauthorized()

    guarded = [Depends(check_token)]

    @app.exception_handler(_Unauthorized)
    async def _unauthorized(request: Request, e: _Unauthorized):
        return error_response(401, "unauthorized", "missing or wrong bearer token",
                              headers={"WWW-Authenticate": "Bearer"})

    @app.exception_handler(ServiceError)
    async def _service(request: Request, e: ServiceError):
        return _service_error(e)

    @app.exception_handler(Exception)
    async def _internal(request: Request, e: Exception):
        # A fault of the server, not of the request (a model error, memory): the same JSON error shape as every
        # other status rather than Starlette's plain-text 500. Starlette raises the exception on after this
        # response, so uvicorn logs its traceback once.
        return error_response(500, "internal", f"{type(e).__name__}: {e}")

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, e: RequestValidationError):
        errs = e.errors()
        field = ".".join(str(p) for p in errs[0]["loc"]) if errs else None
        return error_response(422, "invalid_input", "; ".join(
            f"{'.'.join(str(p) for p in x['loc'])}: {x['msg']}" for x in errs[:5]), field)

    app.add_middleware(_ObserveRequests, metrics=runtime.metrics)

    async def parse(request: Request, model: type[BaseModel]) -> tuple[str, Any]:
        """('json', model instance) or ('npz', {name: array}); 415 for other content types."""
        ctype = request.headers.get("content-type", "application/json").split(";")[0].strip().lower()
        body = await request.body()
        if ctype in BINARY_TYPES:
            return "npz", await wire.off_loop(codecs.load_npz, body, "body")
        if ctype not in ("application/json", ""):
            raise _UnsupportedMedia(ctype)
        try:
            return "json", await wire.off_loop(model.model_validate_json, body)
        except ValidationError as e:
            errs = e.errors()
            loc = ".".join(str(p) for p in errs[0]["loc"]) if errs else "body"
            raise InvalidInput(loc or "body", "; ".join(
                f"{'.'.join(str(p) for p in x['loc']) or 'body'}: {x['msg']}" for x in errs[:5])) from None

    @app.exception_handler(_UnsupportedMedia)
    async def _unsupported(request: Request, e: _UnsupportedMedia):
        return error_response(415, "unsupported_media_type",
                              f"Content-Type {e.args[0]!r}: use application/json or {NPZ}", "content-type")

    def wants_npz(request: Request) -> bool:
        return NPZ in request.headers.get("accept", "")

    def npz_response(answer: Answer, arrays: dict[str, np.ndarray], extra: dict) -> Response:
        meta = {"info": wire.info_dict(answer), **extra}
        return Response(codecs.save_npz({**arrays, "meta_json": np.array(json.dumps(meta))}), media_type=NPZ)

    grid = lambda: runtime.bundle.preset.grid.to_dict()  # noqa: E731 (current bundle's grid)

    def budget() -> codecs.PixelBudget:
        """A fresh request's pixel budget (`serve --max-request-pixels`)."""
        return codecs.PixelBudget(runtime.config.max_request_pixels)

    # ------------------------------------------------------------------------------ routes
    @app.post("/v1/map", dependencies=guarded, response_model=schemas.MapResponseJSON, tags=["inference"],
              summary="Frames of one instant -> occupancy, heightmap (and features) in ref",
              openapi_extra=_request_body_schema(schemas.MapRequestJSON, "arrays rgb, depth, pix_T_cam[, world_T_cam]",
                                                 examples.MAP),
              responses=_ERRORS)
    async def map_route(request: Request,
                        features: Annotated[bool, Query(description="binary bodies: return features")] = False):
        kind, body = await parse(request, schemas.MapRequestJSON)
        if kind == "json":
            item = MapInput(views=await wire.off_loop(wire.views_from_json, body.views, "views", budget()),
                            features=body.features)
        else:
            item = MapInput(views=await wire.off_loop(wire.views_from_npz, body, "", budget()), features=features)
        answer = await runtime.infer("map", item)
        if wants_npz(request):
            return npz_response(answer, wire.map_arrays(answer.result), {"grid": grid()})
        out = {k: wire.tensor_json(v) for k, v in wire.map_arrays(answer.result).items()}
        return {"info": wire.info_dict(answer), "grid": grid(), **out}

    async def pair_item(request: Request, model) -> tuple[Any, Any]:
        """(the JSON body, or None for .npz, (views0, views1))."""
        kind, body = await parse(request, model)

        def decode():
            pixels = budget()   # one request: both instants draw on it
            if kind == "json":
                return (wire.views_from_json(body.views0, "views0", pixels),
                        wire.views_from_json(body.views1, "views1", pixels))
            return wire.views_from_npz(body, "0", pixels), wire.views_from_npz(body, "1", pixels)
        return body if kind == "json" else None, await wire.off_loop(decode)

    @app.post("/v1/egomotion", dependencies=guarded, response_model=schemas.EgomotionResponseJSON, tags=["inference"],
              summary="Frame pair -> cam0_T_cam1 (rigid 4×4)",
              openapi_extra=_request_body_schema(schemas.PairRequestJSON, "arrays rgb0, depth0, pix_T_cam0, rgb1, ...",
                                                 examples.PAIR),
              responses=_ERRORS)
    async def egomotion_route(request: Request):
        _, views = await pair_item(request, schemas.PairRequestJSON)
        answer = await runtime.infer("egomotion", pair_input(*views))
        return {"info": wire.info_dict(answer), "cam0_T_cam1": answer.result.cam0_T_cam1.tolist()}

    @app.post("/v1/flow", dependencies=guarded, response_model=schemas.FlowResponseJSON, tags=["inference"],
              summary="Frame pair -> 3D flow in ref (voxels, t0 -> t1), stabilised as `stabilise` says",
              openapi_extra=_request_body_schema(schemas.FlowRequestJSON, "arrays rgb0, depth0, pix_T_cam0, rgb1, ...",
                                                 examples.FLOW),
              responses=_ERRORS)
    async def flow_route(request: Request,
                         stabilise: Annotated[schemas.Stabilise, Query(description="binary bodies: "
                                                                       + schemas.STABILISE_DOC)] = "poses"):
        body, views = await pair_item(request, schemas.FlowRequestJSON)
        answer = await runtime.infer("flow", flow_input(*views, body.stabilise if body is not None else stabilise))
        if wants_npz(request):
            return npz_response(answer, {"flow": answer.result.flow}, {"grid": grid()})
        return {"info": wire.info_dict(answer), "grid": grid(), "flow": wire.tensor_json(answer.result.flow)}

    def detections_json(answer: Answer, views) -> dict:
        return {"info": wire.info_dict(answer), "frame": answer.frame, "bundle_version": answer.bundle_version,
                "camera_id": views.camera_ids[0] if views.camera_ids else "", "sequence": views.sequence,
                "source_timestamp": views.timestamp, "boxes": wire.boxes_dicts(answer.result, answer.frame)}

    @app.post("/v1/detect", dependencies=guarded, response_model=schemas.DetectionsResponseJSON, tags=["inference"],
              summary="Frames of one instant -> scored 3D boxes in ref",
              openapi_extra=_request_body_schema(schemas.DetectRequestJSON,
                                                 "arrays rgb, depth, pix_T_cam[, world_T_cam]", examples.DETECT),
              responses=_ERRORS)
    async def detect_route(request: Request,
                           min_score: Annotated[float, Query(ge=0, le=1, description="binary bodies")] = 0.0):
        kind, body = await parse(request, schemas.DetectRequestJSON)
        views = await (wire.off_loop(wire.views_from_json, body.views, "views", budget()) if kind == "json"
                       else wire.off_loop(wire.views_from_npz, body, "", budget()))
        score = body.min_score if kind == "json" else check_min_score(min_score)
        answer = await runtime.infer("detect", DetectInput(views=views, min_score=score))
        return detections_json(answer, views)

    @app.post("/v1/moving-objects", dependencies=guarded, response_model=schemas.DetectionsResponseJSON, tags=["inference"],
              summary="Frame pair -> moving objects (oriented boxes with velocities) in ref",
              openapi_extra=_request_body_schema(schemas.MovingObjectsRequestJSON,
                                                 "arrays rgb0, depth0, ..., rgb1, ...", examples.MOVING_OBJECTS),
              responses=_ERRORS)
    async def moving_route(request: Request,
                           min_score: Annotated[float, Query(ge=-1, le=1, description="binary bodies")] = -1.0):
        body, (v0, v1) = await pair_item(request, schemas.MovingObjectsRequestJSON)
        score = body.min_score if body is not None else check_min_score(min_score, low=-1.0)
        item = moving_input(v0, v1, min_score=score, frame_dt=runtime.config.frame_dt, modules=runtime.modules,
                            config=runtime.config.moving_objects)
        answer = await runtime.infer("moving_objects", item)
        return detections_json(answer, v1)  # boxes in ref = views0[0]'s camera; provenance of the newest frame

    @app.get("/v1/models", dependencies=guarded, response_model=schemas.ModelsResponseJSON, tags=["admin"],
             summary="The loaded bundle: version, preset, modules, available routes")
    async def models_route():
        return runtime.describe()

    @app.post("/v1/admin/reload", dependencies=guarded, response_model=schemas.ModelsResponseJSON, tags=["admin"],
              summary="Load a bundle (default: the current directory again); the old one keeps serving on failure",
              responses={409: {"model": schemas.ErrorJSON, "description": "loading failed; old bundle still serves"}})
    async def reload_route(body: Annotated[schemas.ReloadRequestJSON | None,
                                           Body(openapi_examples=examples.RELOAD)] = None):
        try:
            return await runtime.reload(body.bundle if body else None)
        except BundleError as e:
            return error_response(409, "reload_failed", f"{e} (still serving {runtime.version})", "bundle")

    @app.get("/healthz", tags=["probes"], summary="Liveness: the process answers")
    async def healthz():
        return {"status": "ok"}

    @app.get("/readyz", tags=["probes"], summary="Readiness: a bundle is loaded and requests are accepted",
             responses={503: {"model": schemas.ErrorJSON}})
    async def readyz():
        if not runtime.ready:
            return error_response(503, "not_ready", "starting or shutting down")
        return {"status": "ready", "bundle_version": runtime.version, "routes": runtime.routes}

    @app.get("/metrics", tags=["probes"], summary="Prometheus metrics", response_class=Response)
    async def metrics():
        runtime.metrics.queue_depth.set(runtime.queued)
        runtime.metrics.in_flight.set(runtime.in_flight)
        return Response(runtime.metrics.render(), media_type=runtime.metrics.content_type)

    _add_component_schemas(app, extra_models)
    return app


class _ObserveRequests:
    """Pure ASGI middleware counting /v1 requests by route template and status (BaseHTTPMiddleware,
    i.e. @app.middleware, would add a task and a body copy per request)."""

    def __init__(self, app, *, metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = time.perf_counter()
        status = {"code": 500}

        async def send_and_note(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_note)
        finally:
            path = getattr(scope.get("route"), "path", "")
            if path.startswith("/v1/"):
                self.metrics.observe_request("rest", path, str(status["code"]), time.perf_counter() - started)


class _Unauthorized(Exception):
    pass


class _UnsupportedMedia(Exception):
    pass


_ERRORS = {
    401: {"model": schemas.ErrorJSON, "description": "missing or wrong bearer token"},
    404: {"model": schemas.ErrorJSON, "description": "the bundle lacks a module this route needs"},
    413: {"description": "body larger than the server's cap"},
    415: {"model": schemas.ErrorJSON, "description": "unsupported Content-Type"},
    422: {"model": schemas.ErrorJSON, "description": "invalid input; `field` names it"},
    429: {"model": schemas.ErrorJSON, "description": "overloaded: the queue is full"},
    500: {"model": schemas.ErrorJSON, "description": "a fault of the server (error `internal`)"},
    503: {"model": schemas.ErrorJSON, "description": "starting or shutting down"},
    504: {"model": schemas.ErrorJSON, "description": "the request exceeded its deadline"},
}


def _add_component_schemas(app: FastAPI, models) -> None:
    """Put the request models (used only through openapi_extra) into components.schemas."""
    from pydantic.json_schema import models_json_schema

    original = app.openapi

    def openapi():
        if app.openapi_schema:
            return app.openapi_schema
        spec = original()
        _, defs = models_json_schema([(m, "validation") for m in models],
                                     ref_template="#/components/schemas/{model}")
        spec.setdefault("components", {}).setdefault("schemas", {}).update(defs.get("$defs", {}))
        app.openapi_schema = spec
        return spec

    app.openapi = openapi
