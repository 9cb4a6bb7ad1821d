"""A real `n3dmap serve` process: every route and RPC of a full bundle answering what core.pipeline answers
for the same inputs (REST .npz and JSON bodies, gRPC, the gRPC stream), health + reflection, bad inputs and
each refusal naming its field, concurrency, OpenAPI fuzzing. A bundle without some modules answers those
routes 404 / UNIMPLEMENTED."""

from __future__ import annotations

import base64
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import grpc
import httpx
import numpy as np
import pytest

from tests.integration.serve_support import ServerProcess, make_bundle, sample_frames

pytestmark = pytest.mark.integration

ROUTES = {"map": "/v1/map", "egomotion": "/v1/egomotion", "flow": "/v1/flow", "detect": "/v1/detect",
          "moving_objects": "/v1/moving-objects"}


ATOL = 1e-4
MOVERS_SEED = 1  # a synthetic scene whose moving cars the untrained full bundle finds (boxes over STEP s)
# Seconds between the frames below. The untrained bundle's flow is slow: over 0.05 s its movers went at
# 0.71 m/s, under the 1.0 m/s object threshold (core.pipeline.moving_boxes), leaving no boxes to compare.
STEP = 0.025


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serve")
    bundle = make_bundle(tmp / "bundle")
    # --frame-dt STEP as the frames' clock below: the untrained bundle's flow is slow, and 0.2 s steps left
    # it under the speed thresholds (no boxes to compare between the transports).
    # --egomotion-fine module: the routes run the bundle's egomotion module as core.pipeline does (the
    # default, splat, swaps its last stage; the moving-object options test below runs the default)
    with ServerProcess(bundle, "--max-wait-ms", "20", "--frame-dt", str(STEP), "--egomotion-fine", "module",
                       log_path=tmp / "server.log") as s:
        s.bundle = bundle
        yield s


@pytest.fixture(scope="module")
def core_bundle(server):
    """The server's bundle, loaded in this process: the reference answers come from core.pipeline on it."""
    import torch

    from core.bundle import load_bundle

    torch.set_num_threads(1)  # as the server (--threads 1)
    bundle = load_bundle(server.bundle, "cpu")
    for module in bundle.modules.values():
        module.eval()
    return bundle


@pytest.fixture(scope="module")
def rest(server):
    from services.inference.client import RestClient
    with RestClient(server.url) as c:
        yield c


@pytest.fixture(scope="module")
def grpc_client(server):
    from services.inference.client import GrpcClient
    with GrpcClient(server.target) as c:
        yield c


def movers(count: int = 3, *, stamps=None):
    """`count` consecutive single-view client.Frames of a synthetic scene with moving cars (camera cam0,
    sequence i, timestamp stamps[i], default 100 + STEP·i)."""
    from services.inference.client import Frames
    from services.streaming.sources import synthetic_frames

    source = synthetic_frames(preset_name="tiny", seed=MOVERS_SEED, frames_per_episode=8)
    stamps = [100.0 + STEP * i for i in range(count)] if stamps is None else stamps
    return [Frames(rgb=f["rgb"], depth=f["depth"], pix_T_cam=f["pix_T_cam"], world_T_cam=f["world_T_cam"],
                   camera_id="cam0", sequence=i, timestamp=stamps[i]) for i, f in zip(range(count), source)]


def core_inputs(frames, suffix: str = "") -> dict:
    """client.Frames -> the batched tensors core.pipeline takes (B = 1), written out here, not the service's."""
    import torch

    f = frames.batched()
    out = {"rgb": torch.from_numpy(np.asarray(f.rgb, np.uint8)[None]).permute(0, 1, 4, 2, 3).float() / 255.0,
           "depth": torch.from_numpy(np.asarray(f.depth, np.float32)[None]),
           "pix_T_cam": torch.from_numpy(np.asarray(f.pix_T_cam, np.float32)[None]),
           "world_T_cam": torch.from_numpy(np.asarray(f.world_T_cam, np.float32)[None])}
    return {k + suffix: v for k, v in out.items()}


def _stream_dropped(server) -> dict[str, float]:
    """{reason: count} of n3dmap_stream_frames_dropped in the server's /metrics."""
    import re

    text = httpx.get(server.url + "/metrics").text
    return {m["reason"]: float(m["value"]) for m in re.finditer(
        r'^n3dmap_stream_frames_dropped_total\{reason="(?P<reason>\w+)"\} (?P<value>\S+)$', text, re.M)}


def test_a_stream_carries_a_bounded_number_of_cameras(grpc_client):
    from services.inference.client import ServiceCallError
    from services.inference.grpc_server import MAX_STREAM_CAMERAS

    first = movers(1)[0]
    cameras = []
    for i in range(MAX_STREAM_CAMERAS + 1):
        f = copy_frames(first)
        f.camera_id = f"cam{i}"
        cameras.append(f)
    with pytest.raises(ServiceCallError) as e:
        list(grpc_client.stream_moving_objects(cameras))
    assert e.value.status == "RESOURCE_EXHAUSTED" and f"at most {MAX_STREAM_CAMERAS} cameras" in e.value.detail


def test_a_multi_view_frame_is_refused_by_the_stream_client_not_cut_to_its_first_view(grpc_client):
    two_views = sample_frames(views=2)
    with pytest.raises(ValueError, match="single-view Frames; camera 'cam0' sent 2 views"):
        list(grpc_client.stream_moving_objects([two_views]))


def copy_frames(frames):
    import copy

    return copy.copy(frames)


def core_boxes(out: dict, min_score: float) -> dict:
    """core.pipeline's padded boxes of item 0 -> the valid rows scored ≥ min_score, best first (numpy)."""
    import torch

    keep = out["valid"][0] & (out["scores"][0] >= min_score)
    order = torch.argsort(-out["scores"][0][keep], stable=True)
    rows = {k: out[k][0][keep][order].numpy() for k in ("boxes", "scores")}
    rows["velocities"] = out["velocities"][0][keep][order].numpy() if "velocities" in out else np.zeros((len(order), 3))
    return rows


def assert_boxes(got: dict, want: dict) -> None:
    assert got["boxes"].shape == want["boxes"].shape, (got["boxes"].shape, want["boxes"].shape)
    for key in ("boxes", "scores", "velocities"):
        np.testing.assert_allclose(got[key], want[key], atol=ATOL, err_msg=key)


@pytest.fixture(scope="module")
def expected(core_bundle):
    """What core.pipeline answers for the movers pair, route by route."""
    import torch

    from core.pipeline import detect, estimate_egomotion, estimate_flow, map_frames, moving_objects

    f0, f1 = movers(2)
    pair = {**core_inputs(f0, "0"), **core_inputs(f1, "1")}
    with torch.no_grad():
        out = {"map": {k: v[0].numpy() for k, v in map_frames(core_bundle, **core_inputs(f0)).items()},
               "egomotion": estimate_egomotion(core_bundle, **pair)["cam0_T_cam1"][0].numpy(),
               "flow": {mode: estimate_flow(core_bundle, **pair, stabilize=mode)["flow"][0].numpy()
                        for mode in ("poses", "egomotion", "none")},
               "detect": core_boxes(detect(core_bundle, **core_inputs(f0)), 0.0),
               "moving_objects": core_boxes(moving_objects(core_bundle, **pair, dt=f1.timestamp - f0.timestamp), -1.0)}
    assert len(out["moving_objects"]["boxes"]) > 0 and len(out["detect"]["boxes"]) > 0  # boxes to compare
    return out


@pytest.mark.parametrize("transport", ["rest-npz", "rest-json", "grpc"])
def test_every_route_of_a_full_bundle_answers_as_core_pipeline(server, rest, grpc_client, expected, transport):
    from services.inference.client import RestClient
    from services.inference.routes import ROUTES as SERVED

    models = rest.models()
    assert set(models["routes"]) == set(SERVED) == set(ROUTES)  # a full bundle serves every route
    f0, f1 = movers(2)
    client = grpc_client if transport == "grpc" else RestClient(server.url, encoding=transport.split("-")[1])
    try:
        got = client.map(f0, features=True)
        assert got["info"]["bundle_version"] == models["bundle_version"] and got["info"]["frame"] == "ref"
        for key in ("observed", "occupancy", "heightmap"):
            np.testing.assert_allclose(got[key], expected["map"][key][0] if key != "heightmap" else expected["map"][key],
                                       atol=ATOL, err_msg=key)
        np.testing.assert_allclose(got["features"], expected["map"]["features"], atol=ATOL)
        np.testing.assert_allclose(client.egomotion(f0, f1)["cam0_T_cam1"], expected["egomotion"], atol=ATOL)
        for mode, flow in expected["flow"].items():
            np.testing.assert_allclose(client.flow(f0, f1, stabilise=mode)["flow"], flow, atol=ATOL, err_msg=mode)
        np.testing.assert_allclose(client.flow(f0, f1)["flow"], expected["flow"]["poses"], atol=ATOL)  # the default
        assert_boxes(client.detect(f0), expected["detect"])
        moving = client.moving_objects(f0, f1)
        assert moving["frame"] == "ref" and moving["sequence"] == 1 and moving["source_timestamp"] == f1.timestamp
        assert_boxes(moving, expected["moving_objects"])
    finally:
        if isinstance(client, RestClient):
            client.close()


def test_velocities_follow_the_frames_clock(server, rest, grpc_client, core_bundle):
    """The same pair stamped STEP and 2·STEP s apart answers what core.pipeline answers over those intervals
    (the speed thresholds and the velocities scale with the interval); unstamped (both 0), it spans
    (sequence1 − sequence0) × --frame-dt (STEP on this server); with capture times, their interval."""
    import torch

    from core.pipeline import moving_objects

    f0, f1 = movers(2, stamps=[0.0, STEP])
    pair = {**core_inputs(f0, "0"), **core_inputs(f1, "1")}
    answers = {}
    for dt in (STEP, 2 * STEP):
        f1.timestamp = dt
        with torch.no_grad():
            want = core_boxes(moving_objects(core_bundle, **pair, dt=dt), -1.0)
        for client in (rest, grpc_client):
            answers[dt] = client.moving_objects(f0, f1)
            assert_boxes(answers[dt], want)
    assert len(answers[STEP]["boxes"]) > 0  # something to compare
    assert answers[STEP]["boxes"].shape != answers[2 * STEP]["boxes"].shape or not np.allclose(
        answers[STEP]["velocities"], answers[2 * STEP]["velocities"])
    f0.timestamp, f1.timestamp, f0.sequence, f1.sequence = 0.0, 0.0, 3, 5
    for client in (rest, grpc_client):
        assert_boxes(client.moving_objects(f0, f1), answers[2 * STEP])
    # capture times, when both frames carry one, outrank the timestamps (a recording replayed slower)
    from services.inference.client import RestClient

    f0.timestamp, f1.timestamp, f0.capture_time, f1.capture_time = 10.0, 10.0 + 2 * STEP, 50.0, 50.0 + STEP
    with RestClient(server.url, encoding="json") as rest_json:
        for client in (rest, rest_json, grpc_client):   # npz, JSON, protobuf
            assert_boxes(client.moving_objects(f0, f1), answers[STEP])


@pytest.mark.parametrize("encoding,png", [("json", False), ("png", True)])
def test_map_with_json_and_png_encodings_matches_binary(server, rest, encoding, png):
    from services.inference.client import GrpcClient, RestClient

    f = sample_frames(views=2, seed=5)
    f.depth = np.round(f.depth * 1000).astype(np.float32) / np.float32(1000)  # whole mm: PNG is lossless
    want = rest.map(f, features=True)
    with RestClient(server.url, encoding=encoding) as c:
        got = c.map(f, features=True)
    with GrpcClient(server.target, png=png) as g:
        got_grpc = g.map(f, features=True)
    for out in (got, got_grpc):
        assert set(out) >= set(want) - {"meta_json"}
        np.testing.assert_array_equal(out["observed"], want["observed"])
        np.testing.assert_allclose(out["features"], want["features"], atol=1e-5)


def test_models_health_metrics_and_openapi(server, rest, grpc_client):
    m_rest, m_grpc = rest.models(), grpc_client.models()
    assert m_rest["bundle_version"] == m_grpc["bundle_version"] and m_rest["routes"] == m_grpc["routes"]
    assert "mapper" in m_rest["modules"] and m_rest["preset"] == "tiny"
    assert rest.health()["ready"] and grpc_client.health()["status"] == "SERVING"
    assert grpc_client.health("n3dmap.v1.Inference")["ready"]
    rest.map(sample_frames())
    metrics = httpx.get(server.url + "/metrics").text
    for name in ("n3dmap_requests_total", "n3dmap_request_seconds_bucket", "n3dmap_batch_size_bucket",
                 "n3dmap_queue_wait_seconds_bucket"):
        assert name in metrics
    assert 'route="/v1/map",status="200",transport="rest"' in metrics
    spec = httpx.get(server.url + "/openapi.json").json()
    assert set(ROUTES.values()) <= set(spec["paths"]) and "MapRequestJSON" in spec["components"]["schemas"]


def test_reflection_lists_and_describes_the_service(server):
    from google.protobuf import descriptor_pb2
    from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

    with grpc.insecure_channel(server.target) as channel:
        stub = reflection_pb2_grpc.ServerReflectionStub(channel)
        listed = next(iter(stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")]))))
        names = {s.name for s in listed.list_services_response.service}
        assert {"n3dmap.v1.Inference", "grpc.health.v1.Health"} <= names
        answer = next(iter(stub.ServerReflectionInfo(iter([
            reflection_pb2.ServerReflectionRequest(file_containing_symbol="n3dmap.v1.Inference")]))))
        files = [descriptor_pb2.FileDescriptorProto.FromString(b)
                 for b in answer.file_descriptor_response.file_descriptor_proto]
        methods = {m.name for f in files for s in f.service for m in s.method}
        assert {"Map", "Egomotion", "Flow", "Detect", "MovingObjects", "Models", "StreamMovingObjects"} <= methods


def test_stream_follows_the_bridge_rules_and_answers_as_core_pipeline(server, grpc_client, core_bundle):
    """One answer per frame processed: a camera's first frame has no boxes; a duplicate and an out-of-order
    frame get no answer (the bridge drops them); every other answer equals core.pipeline.moving_objects for
    (the previous processed frame, this one) over their timestamps' interval."""
    import copy

    import torch

    from core.pipeline import moving_objects
    from services.inference.client import ServiceCallError

    frames = movers(3, stamps=[100.0, 100.0 + STEP, 100.0 + 3 * STEP])
    duplicate, older = copy.copy(frames[1]), copy.copy(frames[0])
    dropped_before = _stream_dropped(server)
    out = list(grpc_client.stream_moving_objects([frames[0], frames[1], duplicate, older, frames[2]]))
    assert [d["sequence"] for d in out] == [0, 1, 2] and len(out[0]["boxes"]) == 0
    after = _stream_dropped(server)   # the two unanswered frames are counted, by reason
    assert {k: after.get(k, 0) - dropped_before.get(k, 0) for k in ("duplicate", "out_of_order")} == {
        "duplicate": 1, "out_of_order": 1}
    assert all(d["frame"] == "ref" and d["camera_id"] == "cam0" for d in out)
    boxes = 0
    for before, now, answer in zip(frames, frames[1:], out[1:]):
        with torch.no_grad():
            want = moving_objects(core_bundle, **core_inputs(before, "0"), **core_inputs(now, "1"),
                                  dt=now.timestamp - before.timestamp)
        assert_boxes(answer, core_boxes(want, -1.0))
        boxes += len(answer["boxes"])
    assert boxes > 0
    backwards = movers(2, stamps=[100.0, 99.0])
    with pytest.raises(ServiceCallError) as e:
        list(grpc_client.stream_moving_objects(backwards))
    assert e.value.status == "INVALID_ARGUMENT" and e.value.detail.startswith("frame.timestamp")
    # a frame that opens a new recording (its clock restarts) is a cut, answered like a first frame
    cut = movers(3, stamps=[100.0, 100.0 + STEP, 50.0])
    cut[2].scene_start = True
    out = list(grpc_client.stream_moving_objects(cut))
    assert [d["sequence"] for d in out] == [0, 1, 2] and len(out[2]["boxes"]) == 0


def test_stream_numbers_frames_the_caller_left_unnumbered(grpc_client):
    """Frames.sequence None (not set): the client numbers it one past its camera's largest sent so far (0
    first), so every frame is answered; numbered frames are sent as given (a duplicate still gets none)."""
    import copy

    frames = movers(4)
    for f in frames:
        f.sequence = None
    second_camera = copy.copy(frames[1])
    second_camera.camera_id = "cam1"
    out = list(grpc_client.stream_moving_objects(frames[:2] + [second_camera] + frames[2:]))
    assert [(d["camera_id"], d["sequence"]) for d in out] == [("cam0", 0), ("cam0", 1), ("cam1", 0),
                                                                ("cam0", 2), ("cam0", 3)]
    numbered = movers(3)
    numbered[1].sequence = 5
    numbered[2].sequence = None            # after 5: 6
    again = copy.copy(numbered[1])         # 5 again: a duplicate, no answer
    out = list(grpc_client.stream_moving_objects([numbered[0], numbered[1], again, numbered[2]]))
    assert [d["sequence"] for d in out] == [0, 5, 6]


def test_a_stream_outlives_the_clients_per_call_timeout(server):
    """A camera's stream runs as long as it sends: the client's timeout_s bounds unary calls, and a
    stream only when given its own (a stream that outlasts it then ends with DEADLINE_EXCEEDED)."""
    import time

    from services.inference.client import GrpcClient, ServiceCallError

    def slowly(frames):
        for f in frames:
            yield f
            time.sleep(0.6)                 # 3 frames: ~1.8 s, past the 1 s timeout

    with GrpcClient(server.target, timeout_s=1.0) as c:
        out = list(c.stream_moving_objects(slowly(movers(3, stamps=[100.0, 100.0 + STEP, 100.0 + 2 * STEP]))))
        assert [d["sequence"] for d in out] == [0, 1, 2]
        with pytest.raises(ServiceCallError) as e:
            list(c.stream_moving_objects(slowly(movers(3, stamps=[100.0, 100.0 + STEP, 100.0 + 2 * STEP])),
                                         timeout_s=1.0))
        assert e.value.status == "DEADLINE_EXCEEDED"


def test_stream_levelled_by_metadata_answers_as_core_pipeline_in_the_placed_frames(grpc_client, core_bundle):
    """The call's metadata asks for the bridge's --level --level-ahead --ground-y: boxes in each previous frame's
    camera levelled to gravity and placed (core.geometry.poses.level_over_ground), frame "level" with that pose,
    equal to core.pipeline given those map frames. A malformed or orphan option ends the call with
    INVALID_ARGUMENT naming the metadata key."""
    import torch

    from core.geometry.poses import level_over_ground
    from core.pipeline import moving_objects
    from services.inference.client import ServiceCallError

    ahead, ground_y = 12.0, 2.0
    frames = movers(3)
    out = list(grpc_client.stream_moving_objects(frames, level=True, level_ahead=ahead, ground_y=ground_y))
    assert [d["frame"] for d in out] == ["level"] * 3
    boxes = 0
    for before, now, answer in zip(frames, frames[1:], out[1:]):
        inputs = {**core_inputs(before, "0"), **core_inputs(now, "1")}
        placed = {f"world_T_ref{i}": level_over_ground(inputs[f"world_T_cam{i}"][:, 0], ahead=ahead, ground_y=ground_y,
                                                       origin_height=core_bundle.preset.ground_y) for i in (0, 1)}
        np.testing.assert_allclose(answer["world_T_frame"], placed["world_T_ref0"][0].numpy(), atol=1e-5)
        with torch.no_grad():
            want = moving_objects(core_bundle, **inputs, **placed, dt=now.timestamp - before.timestamp)
        assert_boxes(answer, core_boxes(want, -1.0))
        boxes += len(answer["boxes"])
    assert boxes > 0
    for kwargs, key in (({"level_ahead": 5.0}, "n3dmap-level-ahead"), ({"level": True, "level_ahead": -1.0}, "n3dmap-level-ahead")):
        with pytest.raises(ServiceCallError) as e:
            list(grpc_client.stream_moving_objects(movers(2), **kwargs))
        assert e.value.status == "INVALID_ARGUMENT" and e.value.detail.startswith(f"metadata {key}"), e.value.detail


# ------------------------------------------------------------------------------------ bad input


def _frame_json(f, v=0, **over):
    from services.inference.client import RestClient
    encoder = RestClient.__new__(RestClient)  # only its JSON encoder, no connection
    encoder.encoding = "json"
    body = encoder._frame_json(f.batched(), v)
    body.update(over)
    return body


def _raw(arr):
    arr = np.asarray(arr)
    return {"array": {"dtype": arr.dtype.name, "shape": list(arr.shape),
                      "data_b64": base64.b64encode(arr.astype(arr.dtype.newbyteorder("<")).tobytes()).decode()}}


def _bad_cases():
    f = sample_frames(views=1).batched()
    rgb, depth, K = f.rgb[0], f.depth[0], f.pix_T_cam[0]
    nan_depth = depth.copy()
    nan_depth[5, 5] = np.nan
    shear = np.eye(4)
    shear[0, 1] = 0.5
    neg_K = K.copy()
    neg_K[0, 0] = -1
    far = np.eye(4)
    far[2, 3] = 1e39  # finite in JSON (float64), inf as the model's float32
    return {
        "rgb dtype": ({"rgb": _raw(rgb.astype(np.float32))}, "views[0].rgb"),
        "rgb shape": ({"rgb": _raw(rgb[:, :, 0])}, "views[0].rgb"),
        "depth size": ({"depth": _raw(depth[:-1])}, "views[0].depth"),
        "depth dtype": ({"depth": _raw(depth.astype(np.int32))}, "views[0].depth"),
        "byte count": ({"depth": {"array": {"dtype": "float32", "shape": [2, 2], "data_b64": "AAAA"}}},
                       "views[0].depth.array"),
        "non-finite depth": ({"depth": _raw(nan_depth)}, "views[0].depth"),
        "non-rigid pose": ({"world_T_cam": shear.tolist()}, "views[0].world_T_cam"),
        "negative focal": ({"pix_T_cam": neg_K.tolist()}, "views[0].pix_T_cam"),
        "pose past float32": ({"world_T_cam": far.tolist()}, "views[0].world_T_cam"),
        "3x3 intrinsics": ({"pix_T_cam": np.eye(3).tolist()}, "views[0].pix_T_cam"),
        "bad png": ({"rgb": {"png_b64": base64.b64encode(b"\x89PNG\r\n\x1a\n garbage").decode()}},
                    "views[0].rgb.png_b64"),
        "bad base64": ({"rgb": {"png_b64": "***"}}, "views[0].rgb.png_b64"),
        "both encodings": ({"rgb": {"png_b64": "AAAA", **_raw(rgb)}}, "views[0].rgb"),
    }


def test_bad_inputs_are_4xx_naming_the_field_on_both_transports(server, grpc_client):
    from n3dmap.v1 import inference_pb2, types_pb2
    from services.inference import codecs
    from services.inference.client import frame_proto

    f = sample_frames(views=1)
    for name, (over, field) in _bad_cases().items():
        r = httpx.post(server.url + "/v1/map", json={"views": [_frame_json(f, **over)]}, timeout=30)
        assert r.status_code == 422, (name, r.status_code, r.text)
        assert r.json()["field"] == field, (name, r.json())
    # The same kinds of mistakes over gRPC: INVALID_ARGUMENT whose message starts with the field.
    good = frame_proto(f.batched(), 0)
    nan_depth = f.batched().depth[0].copy()
    nan_depth[0, 0] = np.inf
    bad_frames = {
        "views[0].depth.array": types_pb2.Frame(rgb=good.rgb, depth=types_pb2.Image(
            array=types_pb2.Tensor(dtype="float32", shape=[3, 3], data=b"\0" * 7)), pix_T_cam=good.pix_T_cam),
        "views[0].depth": types_pb2.Frame(rgb=good.rgb, depth=types_pb2.Image(array=codecs.numpy_to_tensor(nan_depth)),
                                          pix_T_cam=good.pix_T_cam),
        "views[0].rgb.png": types_pb2.Frame(rgb=types_pb2.Image(png=b"not a png"), depth=good.depth,
                                            pix_T_cam=good.pix_T_cam),
        "views[0].pix_T_cam": types_pb2.Frame(rgb=good.rgb, depth=good.depth),
        "views[0].world_T_cam": types_pb2.Frame(rgb=good.rgb, depth=good.depth, pix_T_cam=good.pix_T_cam,
                                                world_T_cam=codecs.numpy_to_tensor(2 * np.eye(4, dtype=np.float32))),
    }
    with grpc.insecure_channel(server.target) as channel:
        from n3dmap.v1 import inference_pb2_grpc
        stub = inference_pb2_grpc.InferenceStub(channel)
        for field, frame in bad_frames.items():
            with pytest.raises(grpc.RpcError) as e:
                stub.Map(inference_pb2.MapRequest(views=[frame]), timeout=30)
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and e.value.details().startswith(field), \
                (field, e.value.details())
        with pytest.raises(grpc.RpcError) as e:
            stub.Map(inference_pb2.MapRequest(views=[]), timeout=30)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and e.value.details().startswith("views")


def test_a_pose_past_float32_is_refused_not_answered_null(server):
    """A JSON pose entry that is finite as float64 but inf as the model's float32 is a 422 naming the field.
    /v1/egomotion used to answer 200 with a null cam0_T_cam1 (found probing by hand: schemathesis's bodies
    are rarely valid enough elsewhere to reach the poses)."""
    import copy

    from services.inference import examples

    body = copy.deepcopy(examples.PAIR["tiny"]["value"])
    body["views1"][0]["world_T_cam"][2][3] = 1e39
    r = httpx.post(server.url + "/v1/egomotion", json=body, timeout=30)
    assert r.status_code == 422 and r.json()["field"] == "views1[0].world_T_cam", r.text
    assert "float32" in r.json()["detail"]


def test_body_limits_content_types_and_npz_bodies(server):
    big = httpx.post(server.url + "/v1/map", content=b"\0" * (65 * 2**20),
                     headers={"content-type": "application/x-npz"}, timeout=60)
    assert big.status_code == 413
    r = httpx.post(server.url + "/v1/map", content=b"hello", headers={"content-type": "text/plain"})
    assert r.status_code == 415
    r = httpx.post(server.url + "/v1/map", content=b"not a zip", headers={"content-type": "application/x-npz"})
    assert r.status_code == 422 and r.json()["field"] == "body"
    from services.inference import codecs
    f = sample_frames(views=1).batched()
    r = httpx.post(server.url + "/v1/map", content=codecs.save_npz({"rgb": f.rgb, "pix_T_cam": f.pix_T_cam}),
                   headers={"content-type": "application/x-npz"})
    assert r.status_code == 422 and r.json()["field"] == "depth"
    r = httpx.post(server.url + "/v1/map", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422


def test_refusals_name_their_field_on_both_transports(server):
    """What the service used to guess is refused, naming the field: several views of one instant without
    their poses, a flow stabilised with poses it was not given, an unknown stabilisation, a pair whose clock
    goes back."""
    from services.inference.client import GrpcClient, RestClient, ServiceCallError

    def refused(call, field: str) -> None:
        with pytest.raises(ServiceCallError) as e:
            call()
        assert e.value.error == "invalid_input" and e.value.status in (422, "INVALID_ARGUMENT"), e.value
        assert e.value.field == field, (field, e.value.field, e.value.detail)

    two = sample_frames(views=2)
    two.world_T_cam = None
    lone0, lone1 = sample_frames(views=1, seed=0), sample_frames(views=1, seed=1)
    lone0.world_T_cam = lone1.world_T_cam = None
    f0, f1 = movers(2, stamps=[5.0, 4.0])
    for transport in ("json", "npz", "grpc"):
        client = GrpcClient(server.target) if transport == "grpc" else RestClient(server.url, encoding=transport)
        with client:
            refused(lambda: client.map(two), "world_T_cam" if transport == "npz" else "views[0].world_T_cam")
            refused(lambda: client.egomotion(two, two), "world_T_cam0" if transport == "npz" else "views0[0].world_T_cam")
            refused(lambda: client.flow(lone0, lone1), "views0[0].world_T_cam")  # stabilise=poses, the default
            refused(lambda: client.flow(lone0, lone1, stabilise="sideways"),
                    "query.stabilise" if transport == "npz" else "stabilise")  # .npz bodies: a query parameter
            refused(lambda: client.moving_objects(f0, f1), "views1.timestamp")
            assert client.flow(lone0, lone1, stabilise="none")["flow"].shape[0] == 3  # said so: answered
    body = {"views0": [_frame_json(lone0)], "views1": [_frame_json(lone1)], "stabilise": "sideways"}
    r = httpx.post(server.url + "/v1/flow", json=body, timeout=30)
    assert r.status_code == 422 and r.json()["field"] == "stabilise", r.text


def test_a_bundle_without_egomotion_refuses_what_it_would_guess(tmp_path):
    """Mapper, flow and occupancy only: egomotion and detect are 404 / UNIMPLEMENTED; flow stabilised by
    egomotion too; moving objects are stabilised with the poses, so frames without them are refused."""
    from services.inference.client import GrpcClient, RestClient, ServiceCallError

    bundle = make_bundle(tmp_path / "bundle", kinds=("mapper", "flow", "occupancy"))
    f0, f1 = movers(2)
    lone0, lone1 = movers(2)
    lone0.world_T_cam = lone1.world_T_cam = None
    with ServerProcess(bundle, log_path=tmp_path / "server.log") as server, \
            RestClient(server.url) as rest, GrpcClient(server.target) as grpc_client:
        assert set(rest.models()["routes"]) == {"map", "flow", "moving_objects"}
        for client in (rest, grpc_client):
            for call, missing in ((lambda: client.egomotion(f0, f1), "egomotion"), (lambda: client.detect(f0), "detector"),
                                  (lambda: client.flow(f0, f1, stabilise="egomotion"), "egomotion")):
                with pytest.raises(ServiceCallError) as e:
                    call()
                assert e.value.error == "module_unavailable" and missing in e.value.detail
                assert e.value.status in (404, "UNIMPLEMENTED")
            with pytest.raises(ServiceCallError) as e:
                client.moving_objects(lone0, lone1)
            assert e.value.error == "invalid_input" and e.value.field == "views0[0].world_T_cam"
            assert client.moving_objects(f0, f1)["frame"] == "ref"
        with pytest.raises(ServiceCallError) as e:
            list(grpc_client.stream_moving_objects([lone0, lone1]))
        assert e.value.status == "INVALID_ARGUMENT" and e.value.detail.startswith("frame.world_T_cam")


# ------------------------------------------------------------------------------------ load


def test_32_concurrent_clients_get_their_own_answers(server):
    """Mixed REST and gRPC clients at once; each answer equals the same request made alone, so
    micro-batching must have split every batch back correctly."""
    from services.inference.client import GrpcClient, RestClient

    inputs = [sample_frames(views=1, seed=100 + i) for i in range(4)]
    with RestClient(server.url) as c:
        alone = [c.map(f, features=True)["features"] for f in inputs]

    def one(i):
        f = inputs[i % 4]
        if i % 2:
            with GrpcClient(server.target) as g:
                out = g.map(f, features=True)
        else:
            with RestClient(server.url) as c:
                out = c.map(f, features=True)
        return i, out

    with ThreadPoolExecutor(32) as pool:
        results = list(pool.map(one, range(32)))
    for i, out in results:
        np.testing.assert_allclose(out["features"], alone[i % 4], atol=1e-4)
    assert max(out["info"]["batch_size"] for _, out in results) > 1


# ------------------------------------------------------------------------------------ fuzzing


@pytest.mark.slow
def test_schemathesis_finds_no_server_errors(server, tmp_path):
    st = shutil.which("st", path=str(__import__("pathlib").Path(sys.executable).parent))
    if st is None:
        pytest.skip("schemathesis is not installed (pip install -e '.[dev]')")
    proc = subprocess.run([st, "run", server.url + "/openapi.json", "--checks", "not_a_server_error",
                           "--max-examples", "4", "--phases", "examples,fuzzing", "--workers", "1",
                           "--seed", "1", "--request-timeout", "30"],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "passed" in proc.stdout


def test_serve_options_reach_every_route(tmp_path, server):
    """`serve --size-prior L W H --min-object-speed M`: the REST route, the unary and the streaming gRPC call
    answer what core.pipeline answers with that post-processing (amodal boxes of that size, that object
    threshold), not the defaults. `--max-request-pixels N` (here exactly one single-view pair's rgb and depth)
    answers such pairs and refuses a pair of two-view instants on both transports, naming the first image past
    the budget."""
    import torch

    from core.moving.amodal import SizePrior
    from core.pipeline import moving_objects
    from core.pipeline.moving_boxes import MovingObjectsConfig
    from services.inference.client import GrpcClient, RestClient, ServiceCallError
    from services.inference.runtime import _load

    config = MovingObjectsConfig(size_prior=SizePrior.from_size(4.5, 2.0, 1.5), min_object_speed=0.5)
    f0, f1 = movers(2)
    # the bundle as a server with the default --egomotion-fine (splat) loads it
    served = _load(str(server.bundle), torch.device("cpu"), egomotion_fine="splat").bundle
    with torch.no_grad():
        want = core_boxes(moving_objects(served, **core_inputs(f0, "0"), **core_inputs(f1, "1"),
                                         dt=f1.timestamp - f0.timestamp, config=config), -1.0)
        default = core_boxes(moving_objects(served, **core_inputs(f0, "0"), **core_inputs(f1, "1"),
                                            dt=f1.timestamp - f0.timestamp), -1.0)
    assert len(want["boxes"]) > 0  # something to compare, and the options change the answer
    assert want["boxes"].shape != default["boxes"].shape or not np.allclose(want["boxes"], default["boxes"])
    H, W = f0.depth.shape
    two_views = sample_frames("tiny", views=2, seed=0), sample_frames("tiny", views=2, seed=1)
    with ServerProcess(server.bundle, "--max-wait-ms", "20", "--frame-dt", str(STEP), "--size-prior", "4.5", "2.0",
                       "1.5", "--min-object-speed", "0.5", "--max-request-pixels", str(4 * H * W),
                       log_path=tmp_path / "server.log") as s:
        with RestClient(s.url) as rest, GrpcClient(s.target) as grpc_client:
            assert_boxes(rest.moving_objects(f0, f1), want)
            assert_boxes(grpc_client.moving_objects(f0, f1), want)
            streamed = list(grpc_client.stream_moving_objects([f0, f1]))
            # each transport names the image as its encoding carries it: the .npz body's rgb1, the Frame's array
            for client, status, field in ((rest, 422, "rgb1"), (grpc_client, "INVALID_ARGUMENT", "views1[0].rgb.array")):
                with pytest.raises(ServiceCallError) as refused:
                    client.egomotion(*two_views)
                assert (refused.value.error, refused.value.status) == ("invalid_input", status)
                assert refused.value.field == field and "budget" in str(refused.value), refused.value
    assert_boxes(streamed[1], want)
