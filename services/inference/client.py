"""Python SDK of the inference service: `RestClient` and `GrpcClient` with the same methods.

    from services.inference.client import Frames, RestClient, GrpcClient
    frames = Frames(rgb=rgb, depth=depth, pix_T_cam=K)          # numpy; V×… or one view
    with RestClient("http://127.0.0.1:8000") as c:              # or GrpcClient("127.0.0.1:50051")
        out = c.map(frames)                                     # {"occupancy": Z×Y×X, "heightmap": …, "info": …}
        boxes = c.moving_objects(frames_t0, frames_t1)["boxes"]  # K×7 in out["frame"]

Every failure the service reports raises `ServiceCallError` with the same `error` names on both
transports: invalid_input (with `field`), module_unavailable, overloaded, timeout, not_ready,
unauthorized, reload_failed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from services.inference import codecs

JSON = "application/json"
NPZ = "application/x-npz"


@dataclass
class Frames:
    """Views of one instant: rgb V×H×W×3 uint8, depth V×H×W float32 metres (0 = missing), pix_T_cam
    V×4×4, world_T_cam V×4×4 (None = identity). A single view may drop the leading V."""

    rgb: np.ndarray
    depth: np.ndarray
    pix_T_cam: np.ndarray
    world_T_cam: np.ndarray | None = None
    camera_id: str = ""
    sequence: int | None = None    # None: not set — sent as 0; a stream numbers it after its camera's last frame
    timestamp: float = 0.0
    capture_time: float = 0.0      # when the scene was seen (0: not given); times motion when both have one
    scene_start: bool = False      # streams: a cut to a new scene (not paired with the camera's previous frame)

    def batched(self) -> "Frames":
        """The same views with the leading V axis present."""
        rgb, depth, K = np.asarray(self.rgb), np.asarray(self.depth), np.asarray(self.pix_T_cam)
        pose = None if self.world_T_cam is None else np.asarray(self.world_T_cam)
        if rgb.ndim == 3:
            rgb, depth, K = rgb[None], depth[None], K[None]                 # 1×H×W×3, 1×H×W, 1×4×4
            pose = None if pose is None else pose[None]                    # 1×4×4
        return Frames(rgb, depth, K, pose, self.camera_id, self.sequence, self.timestamp, self.capture_time,
                      self.scene_start)


class ServiceCallError(Exception):
    """The service answered with an error. `error` is the same name on REST and gRPC."""

    def __init__(self, error: str, detail: str, *, field: str | None = None, status: int | str | None = None):
        super().__init__(f"{error}: {detail}")
        self.error, self.detail, self.field, self.status = error, detail, field, status


def _boxes_from_dicts(boxes: list[dict]) -> dict:
    return {"boxes": np.array([[b[k] for k in ("x", "y", "z", "lx", "ly", "lz", "yaw")] for b in boxes],
                              np.float32).reshape(-1, 7),
            "scores": np.array([b["score"] for b in boxes], np.float32),
            "velocities": np.array([[b["vx"], b["vy"], b["vz"]] for b in boxes], np.float32).reshape(-1, 3),
            "labels": [b["label"] for b in boxes]}


# ------------------------------------------------------------------------------------------ REST


class RestClient:
    """REST client. `encoding`: "npz" (binary bodies, fastest), "json" (base64 arrays) or "png"
    (JSON with PNG images; depth quantised to millimetres)."""

    def __init__(self, base_url: str, *, token: str | None = None, timeout_s: float = 60.0,
                 encoding: str = "npz", verify: bool | str = True):
        import httpx

        if encoding not in ("npz", "json", "png"):
            raise ValueError(f"encoding must be npz, json or png, got {encoding!r}")
        headers = {"authorization": f"Bearer {token}"} if token else {}
        self.encoding = encoding
        self._http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout_s, verify=verify)

    def close(self) -> None:
        self._http.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # --- encoding --------------------------------------------------------------------------
    def _frame_json(self, f: Frames, v: int) -> dict:
        rgb, depth = np.ascontiguousarray(f.rgb[v], np.uint8), np.asarray(f.depth[v], np.float32)
        if self.encoding == "png":
            images = {"rgb": {"png_b64": codecs.b64encode(codecs.encode_png_rgb(rgb))},
                      "depth": {"png_b64": codecs.b64encode(codecs.encode_png_depth(depth))}}
        else:
            images = {"rgb": {"array": _tensor_json(rgb)}, "depth": {"array": _tensor_json(depth)}}
        return {**images, "pix_T_cam": np.asarray(f.pix_T_cam[v], np.float64).tolist(),
                "world_T_cam": None if f.world_T_cam is None else np.asarray(f.world_T_cam[v], np.float64).tolist(),
                "camera_id": f.camera_id, "sequence": int(f.sequence or 0), "timestamp": float(f.timestamp),
                "capture_time": float(f.capture_time)}

    def _views_json(self, frames: Frames) -> list[dict]:
        f = frames.batched()
        return [self._frame_json(f, v) for v in range(f.rgb.shape[0])]

    @staticmethod
    def _views_npz(frames: Frames, suffix: str = "") -> dict[str, np.ndarray]:
        f = frames.batched()
        out = {f"rgb{suffix}": np.asarray(f.rgb, np.uint8), f"depth{suffix}": np.asarray(f.depth, np.float32),
               f"pix_T_cam{suffix}": np.asarray(f.pix_T_cam, np.float32)}
        if f.world_T_cam is not None:
            out[f"world_T_cam{suffix}"] = np.asarray(f.world_T_cam, np.float32)
        out[f"timestamp{suffix}"], out[f"sequence{suffix}"] = np.float64(f.timestamp), np.uint64(f.sequence or 0)
        out[f"capture_time{suffix}"] = np.float64(f.capture_time)
        return out

    def _post(self, path: str, *, json_body: dict, npz_arrays: dict, params: dict | None = None,
              want_npz: bool = False):
        headers = {"accept": NPZ if want_npz else JSON}
        if self.encoding == "npz":
            r = self._send("POST", path, content=codecs.save_npz(npz_arrays), params=params,
                           headers={**headers, "content-type": NPZ})
        else:
            r = self._send("POST", path, json=json_body, headers=headers)
        return self._decode(r)

    def _send(self, method: str, path: str, **kwargs):
        """One HTTP request; a transport failure is a ServiceCallError with the gRPC client's names for the same
        conditions ("timeout"; "not_ready" when the server cannot be reached), not an httpx exception."""
        import httpx

        try:
            return self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as e:
            raise ServiceCallError("timeout", f"{method} {path}: no answer within the client's timeout ({e})") from None
        except httpx.TransportError as e:
            raise ServiceCallError("not_ready", f"{method} {path}: cannot reach the server ({e})") from None

    @staticmethod
    def _decode(r):
        if r.status_code >= 400:
            try:
                body = r.json()
            except ValueError:
                body = {}
            if not isinstance(body, dict) or "error" not in body:
                raise ServiceCallError(f"http_{r.status_code}", r.text[:500], status=r.status_code)
            raise ServiceCallError(body["error"], body.get("detail", ""), field=body.get("field"), status=r.status_code)
        if r.headers.get("content-type", "").startswith(NPZ):
            arrays = codecs.load_npz(r.content, "response")
            meta = json.loads(str(arrays.pop("meta_json")))
            return {**meta, **arrays}
        out = r.json()
        return {k: _from_tensor_json(v) if isinstance(v, dict) and "data_b64" in v else v for k, v in out.items()}

    # --- API -------------------------------------------------------------------------------
    def map(self, frames: Frames, *, features: bool = False) -> dict:
        """-> {"observed": Z×Y×X, ["occupancy": Z×Y×X, "heightmap": Z×X] (with an occupancy head),
        ["features": F×Z×Y×X], "grid", "info"}."""
        return self._post("/v1/map", json_body={"views": self._views_json(frames), "features": features},
                          npz_arrays=self._views_npz(frames), params={"features": str(features).lower()},
                          want_npz=True)

    def _pair_bodies(self, frames0: Frames, frames1: Frames, **extra) -> dict:
        return {"json_body": {"views0": self._views_json(frames0), "views1": self._views_json(frames1), **extra},
                "npz_arrays": {**self._views_npz(frames0, "0"), **self._views_npz(frames1, "1")},
                "params": extra or None}

    def egomotion(self, frames0: Frames, frames1: Frames) -> dict:
        """-> {"cam0_T_cam1": 4×4, "info"}."""
        out = self._post("/v1/egomotion", **self._pair_bodies(frames0, frames1))
        out["cam0_T_cam1"] = np.asarray(out["cam0_T_cam1"], np.float32)
        return out

    def flow(self, frames0: Frames, frames1: Frames, *, stabilise: str = "poses") -> dict:
        """-> {"flow": 3×Z×Y×X (voxels, channels x, y, z), "grid", "info"}. stabilise: "egomotion", "poses"
        (frames0 and frames1 then need world_T_cam) or "none"."""
        return self._post("/v1/flow", **self._pair_bodies(frames0, frames1, stabilise=stabilise), want_npz=True)

    def detect(self, frames: Frames, *, min_score: float = 0.0) -> dict:
        """-> {"boxes": K×7, "scores": K, "velocities": K×3, "labels", "frame", "bundle_version", "info", ...}."""
        out = self._post("/v1/detect", json_body={"views": self._views_json(frames), "min_score": min_score},
                         npz_arrays=self._views_npz(frames), params={"min_score": min_score})
        return {**out, **_boxes_from_dicts(out["boxes"])}

    def moving_objects(self, frames0: Frames, frames1: Frames, *, min_score: float = -1.0) -> dict:
        """Boxes in ref = camera of frames0's view 0, scores (center-surround saliency in [−1, 1]),
        velocities K×3 m/s."""
        out = self._post("/v1/moving-objects", **self._pair_bodies(frames0, frames1, min_score=min_score))
        return {**out, **_boxes_from_dicts(out["boxes"])}

    def models(self) -> dict:
        return self._decode(self._send("GET", "/v1/models"))

    def reload(self, bundle: str | None = None) -> dict:
        return self._decode(self._send("POST", "/v1/admin/reload", json={"bundle": bundle}))

    def health(self) -> dict:
        """-> {"live": bool, "ready": bool, ...readyz body}."""
        import httpx

        try:
            live = self._http.get("/healthz").status_code == 200
            r = self._http.get("/readyz")
        except httpx.TransportError as e:   # as the gRPC client's health(): an answer, not an exception
            return {"live": False, "ready": False, "status": f"unreachable ({type(e).__name__})"}
        return {"live": live, "ready": r.status_code == 200, **r.json()}


def _tensor_json(arr: np.ndarray) -> dict:
    dtype, shape, data = codecs.array_to_bytes(arr)
    return {"dtype": dtype, "shape": shape, "data_b64": codecs.b64encode(data)}


def _from_tensor_json(t: dict) -> np.ndarray:
    return codecs.array_from_bytes(codecs.b64decode(t["data_b64"], "response"), t["dtype"], t["shape"], "response")


# ------------------------------------------------------------------------------------------ gRPC


_GRPC_ERRORS = {"INVALID_ARGUMENT": "invalid_input", "UNIMPLEMENTED": "module_unavailable",
                "RESOURCE_EXHAUSTED": "overloaded", "DEADLINE_EXCEEDED": "timeout", "UNAVAILABLE": "not_ready",
                "UNAUTHENTICATED": "unauthorized"}


def frame_proto(f: Frames, v: int, *, png: bool = False):
    """View v of `f` (batched) -> n3dmap.v1.Frame."""
    from n3dmap.v1 import types_pb2

    rgb, depth = np.ascontiguousarray(f.rgb[v], np.uint8), np.asarray(f.depth[v], np.float32)
    if png:
        rgb_img = types_pb2.Image(png=codecs.encode_png_rgb(rgb))
        depth_img = types_pb2.Image(png=codecs.encode_png_depth(depth))
    else:
        rgb_img = types_pb2.Image(array=codecs.numpy_to_tensor(rgb))
        depth_img = types_pb2.Image(array=codecs.numpy_to_tensor(depth))
    return types_pb2.Frame(
        rgb=rgb_img, depth=depth_img, pix_T_cam=codecs.numpy_to_tensor(np.asarray(f.pix_T_cam[v], np.float32)),
        world_T_cam=None if f.world_T_cam is None else codecs.numpy_to_tensor(np.asarray(f.world_T_cam[v], np.float32)),
        camera_id=f.camera_id, sequence=int(f.sequence or 0), timestamp=float(f.timestamp),
        capture_time=float(f.capture_time), scene_start=bool(f.scene_start))


def _info(msg) -> dict:
    return {"bundle_version": msg.bundle_version, "frame": msg.frame, "model_s": msg.model_s,
            "queue_s": msg.queue_s, "batch_size": msg.batch_size}


def _grid(msg) -> dict:
    return {k: getattr(msg, k) for k in ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax", "Z", "Y", "X")}


def detections_dict(d) -> dict:
    """n3dmap.v1.Detections -> plain dict with numpy boxes (as the REST client returns), plus world_T_frame (4×4 numpy,
    the pose of the boxes' frame; None when the answer carries none)."""
    boxes = [{k: getattr(b, k) for k in ("x", "y", "z", "lx", "ly", "lz", "yaw", "score", "label", "vx", "vy", "vz")}
             for b in d.boxes]
    world_T_frame = codecs.tensor_to_numpy(d.world_T_frame, "world_T_frame") if d.HasField("world_T_frame") else None
    return {"frame": d.frame, "bundle_version": d.bundle_version, "camera_id": d.camera_id, "sequence": d.sequence,
            "source_timestamp": d.source_timestamp, "latency_s": d.latency_s, "world_T_frame": world_T_frame,
            **_boxes_from_dicts(boxes)}


class GrpcClient:
    """gRPC client (sync). `png=True` sends images as PNG (depth quantised to millimetres)."""

    def __init__(self, target: str, *, token: str | None = None, timeout_s: float = 60.0, png: bool = False,
                 root_certificates: bytes | None = None):
        import grpc

        from n3dmap.v1 import inference_pb2_grpc
        from services.inference.grpc_server import channel_options

        self._grpc = grpc
        if root_certificates is not None:
            creds = grpc.ssl_channel_credentials(root_certificates=root_certificates)
            self._channel = grpc.secure_channel(target, creds, options=channel_options())
        else:
            self._channel = grpc.insecure_channel(target, options=channel_options())
        self._stub = inference_pb2_grpc.InferenceStub(self._channel)
        self._metadata = (("authorization", f"Bearer {token}"),) if token else ()
        self._timeout_s, self._png = timeout_s, png

    def close(self) -> None:
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _call(self, method, request):
        try:
            return method(request, timeout=self._timeout_s, metadata=self._metadata)
        except self._grpc.RpcError as e:
            code = e.code().name
            detail = e.details() or ""
            field = detail.split(":", 1)[0] if code == "INVALID_ARGUMENT" and ":" in detail else None
            raise ServiceCallError(_GRPC_ERRORS.get(code, code.lower()), detail, field=field, status=code) from None

    def _views(self, frames: Frames) -> list:
        f = frames.batched()
        return [frame_proto(f, v, png=self._png) for v in range(f.rgb.shape[0])]

    def map(self, frames: Frames, *, features: bool = False) -> dict:
        from n3dmap.v1 import inference_pb2

        r = self._call(self._stub.Map, inference_pb2.MapRequest(views=self._views(frames), features=features))
        out = {"info": _info(r.info), "grid": _grid(r.grid)}
        for name in ("observed", "occupancy", "heightmap", "features"):
            if r.HasField(name):
                out[name] = codecs.tensor_to_numpy(getattr(r, name), name)
        return out

    def _pair(self, frames0: Frames, frames1: Frames):
        from n3dmap.v1 import inference_pb2

        return inference_pb2.PairRequest(views0=self._views(frames0), views1=self._views(frames1))

    def egomotion(self, frames0: Frames, frames1: Frames) -> dict:
        r = self._call(self._stub.Egomotion, self._pair(frames0, frames1))
        return {"info": _info(r.info), "cam0_T_cam1": codecs.tensor_to_numpy(r.cam0_T_cam1, "cam0_T_cam1")}

    def flow(self, frames0: Frames, frames1: Frames, *, stabilise: str = "poses") -> dict:
        from n3dmap.v1 import inference_pb2

        # an unknown name travels as enum value -1, which the server refuses naming `stabilise`
        mode = {"egomotion": inference_pb2.STABILISE_EGOMOTION, "poses": inference_pb2.STABILISE_POSES,
                "none": inference_pb2.STABILISE_NONE}.get(stabilise, -1)
        req = inference_pb2.FlowRequest(views0=self._views(frames0), views1=self._views(frames1), stabilise=mode)
        r = self._call(self._stub.Flow, req)
        return {"info": _info(r.info), "grid": _grid(r.grid), "flow": codecs.tensor_to_numpy(r.flow, "flow")}

    def detect(self, frames: Frames, *, min_score: float = 0.0) -> dict:
        from n3dmap.v1 import inference_pb2

        r = self._call(self._stub.Detect, inference_pb2.DetectRequest(views=self._views(frames), min_score=min_score))
        return {"info": _info(r.info), **detections_dict(r.detections)}

    def moving_objects(self, frames0: Frames, frames1: Frames, *, min_score: float = -1.0) -> dict:
        from n3dmap.v1 import inference_pb2

        req = inference_pb2.MovingObjectsRequest(views0=self._views(frames0), views1=self._views(frames1),
                                                 min_score=min_score)
        r = self._call(self._stub.MovingObjects, req)
        return {"info": _info(r.info), **detections_dict(r.detections)}

    def stream_moving_objects(self, frames, *, level: bool = False, level_ahead: float | None = None,
                              ground_y: float | None = None, timeout_s: float | None = None):
        """Iterable of single-view Frames -> iterator of detections dicts: one per frame, but none for a frame
        whose sequence number is not past its camera's last one (dropped as a duplicate or out of order). A
        frame whose `sequence` is None (not set) is numbered one past the largest its camera sent before (0
        for its first), so a caller that never numbers frames gets an answer to each.
        level / level_ahead / ground_y: the zenoh bridge's --level / --level-ahead / --ground-y (boxes in each
        frame's camera levelled to gravity, frame "level", its pose in the dict's world_T_frame), sent as the
        call's metadata (services.inference.stream_options). timeout_s: a deadline for the whole stream
        (default none: a camera's stream runs as long as it sends; the client's timeout_s is per unary call)."""
        from services.inference.stream_options import stream_metadata

        metadata = self._metadata + stream_metadata(level=level, level_ahead=level_ahead, ground_y=ground_y)

        refused: list[ValueError] = []

        def requests():
            last: dict[str, int] = {}   # camera_id -> the largest sequence number sent so far
            for f in frames:
                f = f.batched()
                if f.rgb.shape[0] != 1:   # a stream frame is one view: the rest would be dropped unsent
                    refused.append(ValueError(f"stream_moving_objects takes single-view Frames; camera {f.camera_id!r} "
                                              f"sent {f.rgb.shape[0]} views (send each camera as its own camera_id)"))
                    return
                if f.sequence is None:  # not set: the next number after the camera's last, so that it is answered
                    f.sequence = last[f.camera_id] + 1 if f.camera_id in last else 0
                last[f.camera_id] = max(last.get(f.camera_id, f.sequence), f.sequence)
                yield frame_proto(f, 0, png=self._png)
        call = self._stub.StreamMovingObjects(requests(), timeout=timeout_s, metadata=metadata)
        try:
            for d in call:
                yield detections_dict(d)
            if refused:
                raise refused[0]
        except self._grpc.RpcError as e:
            code = e.code().name
            raise ServiceCallError(_GRPC_ERRORS.get(code, code.lower()), e.details() or "", status=code) from None
        finally:   # a caller that stops iterating early ends the call now, not when the generator is collected
            call.cancel()

    def models(self) -> dict:
        from n3dmap.v1 import inference_pb2

        r = self._call(self._stub.Models, inference_pb2.ModelsRequest())
        return {"bundle_version": r.bundle_version, "preset": r.preset, "modules": list(r.modules),
                "routes": list(r.routes), "grid": _grid(r.grid), "device": r.device, "meta_json": r.meta_json}

    def health(self, service: str = "") -> dict:
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        stub = health_pb2_grpc.HealthStub(self._channel)
        try:
            r = stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=self._timeout_s)
        except self._grpc.RpcError as e:
            return {"live": False, "ready": False, "status": e.code().name}
        status = health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)
        return {"live": True, "ready": status == "SERVING", "status": status}
