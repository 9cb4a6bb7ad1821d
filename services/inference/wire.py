"""Request decoding and response encoding shared by the transports (JSON, .npz bodies, protobuf).

Decoders turn wire messages into validated `Views` (naming fields like `views0[1].depth` on error);
encoders turn route results (routes.py) into JSON dicts or protobuf messages.
"""

from __future__ import annotations

import asyncio

import numpy as np

from n3dmap.v1 import inference_pb2, types_pb2
from services.inference import codecs
from services.inference.errors import InvalidInput
from services.inference.routes import DetectionsResult, MapResult
from services.inference.runtime import Answer
from services.inference.validation import Views, View, check_view_count, make_view, stack_views


async def off_loop(fn, *args):
    """fn(*args) on a worker thread: decoding and validating a request body (JSON parsing, base64, PNG, .npz,
    per-view checks) is CPU work of up to seconds for a large body, and on the event loop it would stall every
    other request, the gRPC server that shares the loop, and the liveness probe."""
    return await asyncio.to_thread(fn, *args)


# ---------------------------------------------------------------------------------- JSON in


def _json_image(img, field: str, *, depth: bool, budget: codecs.PixelBudget) -> np.ndarray:
    if (img.png_b64 is None) == (img.array is None):
        raise InvalidInput(field, "give exactly one of png_b64 or array")
    if img.png_b64 is not None:
        data = codecs.b64decode(img.png_b64, f"{field}.png_b64")
        return (codecs.decode_png_depth if depth else codecs.decode_png_rgb)(data, f"{field}.png_b64", budget)
    t = img.array
    budget.take(codecs.image_pixels(t.shape), f"{field}.array")
    return codecs.array_from_bytes(codecs.b64decode(t.data_b64, f"{field}.array.data_b64"), t.dtype, t.shape,
                                   f"{field}.array")


def _json_matrix(m, field: str) -> np.ndarray:
    if len(m) != 4 or any(len(row) != 4 for row in m):
        raise InvalidInput(field, f"must be a 4×4 nested list, got {len(m)} rows")
    return np.asarray(m, dtype=np.float64)


def views_from_json(frames, field: str, budget: codecs.PixelBudget | None = None) -> Views:
    """list[FrameJSON] -> Views; `budget`: the request's pixel budget (a pair's two instants share one)."""
    budget = budget or codecs.PixelBudget()
    views = []
    for i, f in enumerate(frames):
        at = f"{field}[{i}]"
        views.append(make_view(
            rgb=_json_image(f.rgb, f"{at}.rgb", depth=False, budget=budget),
            depth=_json_image(f.depth, f"{at}.depth", depth=True, budget=budget),
            pix_T_cam=_json_matrix(f.pix_T_cam, f"{at}.pix_T_cam"),
            world_T_cam=None if f.world_T_cam is None else _json_matrix(f.world_T_cam, f"{at}.world_T_cam"),
            field=at, camera_id=f.camera_id, sequence=f.sequence, timestamp=f.timestamp,
            capture_time=f.capture_time))
    return stack_views(views, field)


# ---------------------------------------------------------------------------------- .npz in


def _npz_scalar(arrays: dict[str, np.ndarray], name: str, kind: str, default):
    """An optional scalar member of a .npz body: one number of dtype kind `kind` ("f" or "iu")."""
    if name not in arrays:
        return default
    arr = arrays[name]
    if arr.size != 1 or arr.dtype.kind not in kind + ("iu" if kind == "f" else ""):
        raise InvalidInput(name, f"must be one {'number' if kind == 'f' else 'integer'}, got dtype {arr.dtype} "
                                 f"shape {list(arr.shape)}")
    value = arr.reshape(()).item()
    if kind == "f" and not np.isfinite(value):
        raise InvalidInput(name, f"must be finite, got {value}")
    if kind == "iu" and value < 0:
        raise InvalidInput(name, f"must be ≥ 0, got {value}")
    return value


def views_from_npz(arrays: dict[str, np.ndarray], suffix: str = "",
                   budget: codecs.PixelBudget | None = None) -> Views:
    """`.npz` body -> Views, charged to the request's pixel `budget` (a pair's two instants share one). Keys: rgb{s} V×H×W×3 uint8, depth{s} V×H×W (float32 m | uint16 mm),
    pix_T_cam{s} V×4×4, world_T_cam{s} V×4×4 (optional for one view), and the optional scalars
    timestamp{s} and capture_time{s} (seconds) and sequence{s} of the instant; `s` is "" for one instant,
    "0"/"1" for pairs."""
    names = {k: f"{k}{suffix}" for k in ("rgb", "depth", "pix_T_cam", "world_T_cam")}
    for k in ("rgb", "depth", "pix_T_cam"):
        if names[k] not in arrays:
            raise InvalidInput(names[k], f"missing from the .npz body (has {sorted(arrays)})")
    rgb, depth, K = arrays[names["rgb"]], arrays[names["depth"]], arrays[names["pix_T_cam"]]
    pose = arrays.get(names["world_T_cam"])
    if rgb.ndim != 4:
        raise InvalidInput(names["rgb"], f"must have shape V×H×W×3, got {list(rgb.shape)}")
    V = rgb.shape[0]
    check_view_count(V, f"views{suffix}")
    if pose is None and V > 1:
        raise InvalidInput(names["world_T_cam"], f"missing: each of the {V} views of one instant needs its camera "
                                                 "pose to be fused with the others")
    for name, arr, ndim in ((names["depth"], depth, 3), (names["pix_T_cam"], K, 3), (names["world_T_cam"], pose, 3)):
        if arr is not None and (arr.ndim != ndim or arr.shape[0] != V):
            raise InvalidInput(name, f"must have {ndim} dims with V={V} first, got {list(arr.shape)}")
    budget = budget or codecs.PixelBudget()
    for name, arr in ((names["rgb"], rgb), (names["depth"], depth)):
        budget.take(V * codecs.image_pixels(arr.shape[1:]), name)
    timestamp = _npz_scalar(arrays, f"timestamp{suffix}", "f", 0.0)
    capture_time = _npz_scalar(arrays, f"capture_time{suffix}", "f", 0.0)
    sequence = _npz_scalar(arrays, f"sequence{suffix}", "iu", 0)
    views = [make_view(rgb=rgb[v], depth=depth[v], pix_T_cam=K[v], world_T_cam=None if pose is None else pose[v],
                       field=f"views{suffix}[{v}]", sequence=sequence, timestamp=timestamp,
                       capture_time=capture_time) for v in range(V)]
    return stack_views(views, f"views{suffix}")


# ---------------------------------------------------------------------------------- protobuf in


def _proto_image(img: types_pb2.Image, field: str, *, depth: bool, budget: codecs.PixelBudget) -> np.ndarray:
    which = img.WhichOneof("encoding")
    if which is None:
        raise InvalidInput(field, "missing (give png or array)")
    if which == "png":
        return (codecs.decode_png_depth if depth else codecs.decode_png_rgb)(img.png, f"{field}.png", budget)
    budget.take(codecs.image_pixels(img.array.shape), f"{field}.array")
    return codecs.tensor_to_numpy(img.array, f"{field}.array")


def view_from_proto(frame: types_pb2.Frame, field: str, budget: codecs.PixelBudget | None = None) -> View:
    """One Frame -> View, charged to `budget` (default: a budget of its own, as a stream frame has)."""
    if not frame.HasField("pix_T_cam"):
        raise InvalidInput(f"{field}.pix_T_cam", "missing")
    budget = budget or codecs.PixelBudget()
    return make_view(
        rgb=_proto_image(frame.rgb, f"{field}.rgb", depth=False, budget=budget),
        depth=_proto_image(frame.depth, f"{field}.depth", depth=True, budget=budget),
        pix_T_cam=codecs.tensor_to_numpy(frame.pix_T_cam, f"{field}.pix_T_cam"),
        world_T_cam=(codecs.tensor_to_numpy(frame.world_T_cam, f"{field}.world_T_cam")
                     if frame.HasField("world_T_cam") else None),
        field=field, camera_id=frame.camera_id, sequence=frame.sequence, timestamp=frame.timestamp,
        scene_start=frame.scene_start, capture_time=frame.capture_time)


def views_from_proto(frames, field: str, budget: codecs.PixelBudget | None = None) -> Views:
    """Repeated Frame -> Views; `budget`: the request's pixel budget (a pair's two instants share one)."""
    check_view_count(len(frames), field)
    budget = budget or codecs.PixelBudget()
    return stack_views([view_from_proto(f, f"{field}[{i}]", budget) for i, f in enumerate(frames)], field)


# ---------------------------------------------------------------------------------- out


def info_dict(answer: Answer) -> dict:
    return {"bundle_version": answer.bundle_version, "frame": answer.frame, "model_s": answer.stats.model_s,
            "queue_s": answer.stats.queue_s, "batch_size": answer.stats.batch_size}


def tensor_json(arr: np.ndarray) -> dict:
    dtype, shape, data = codecs.array_to_bytes(arr)
    return {"dtype": dtype, "shape": shape, "data_b64": codecs.b64encode(data)}


def boxes_dicts(result: DetectionsResult, frame: str) -> list[dict]:
    return [{"x": float(b[0]), "y": float(b[1]), "z": float(b[2]), "lx": float(b[3]), "ly": float(b[4]),
             "lz": float(b[5]), "yaw": float(b[6]), "frame": frame, "score": float(s), "label": label,
             "vx": float(v[0]), "vy": float(v[1]), "vz": float(v[2])}
            for b, s, v, label in zip(result.boxes, result.scores, result.velocities, result.labels)]


def map_arrays(result: MapResult) -> dict[str, np.ndarray]:
    """The arrays a map answer holds (occupancy and heightmap only with an occupancy head)."""
    out = {"observed": result.observed, "occupancy": result.occupancy, "heightmap": result.heightmap,
           "features": result.features}
    return {k: v for k, v in out.items() if v is not None}


def info_proto(answer: Answer) -> inference_pb2.ResponseInfo:
    return inference_pb2.ResponseInfo(**info_dict(answer))


def grid_proto(grid_dict: dict) -> inference_pb2.Grid:
    return inference_pb2.Grid(**grid_dict)


def detections_proto(result: DetectionsResult, *, frame: str, bundle_version: str, views: Views,
                     ref_views: Views | None = None, latency_s: float = 0.0) -> types_pb2.Detections:
    """Boxes in `ref` = the camera of `ref_views[0]` (default `views[0]`); camera id, sequence and
    timestamp come from `views` (the newest frame of a pair)."""
    ref_views = views if ref_views is None else ref_views
    return types_pb2.Detections(
        boxes=[types_pb2.Box3D(**b) for b in boxes_dicts(result, frame)], frame=frame,
        bundle_version=bundle_version, camera_id=views.camera_ids[0] if views.camera_ids else "",
        sequence=views.sequence, source_timestamp=views.timestamp, latency_s=latency_s,
        world_T_frame=codecs.numpy_to_tensor(ref_views.world_T_cam[0]))
