"""A real `n3dmap serve` process: every route and RPC, health + reflection, bad inputs, concurrency,
OpenAPI fuzzing. Routes whose module the bundle lacks must answer 404 / UNIMPLEMENTED."""

from __future__ import annotations

import base64
import json
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


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serve")
    bundle = make_bundle(tmp / "bundle")
    with ServerProcess(bundle, "--max-wait-ms", "20", log_path=tmp / "server.log") as s:
        yield s


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


def _call(client, route: str, f0, f1):
    return {"map": lambda: client.map(f0, features=True), "egomotion": lambda: client.egomotion(f0, f1),
            "flow": lambda: client.flow(f0, f1), "detect": lambda: client.detect(f0),
            "moving_objects": lambda: client.moving_objects(f0, f1)}[route]()


def _check_answer(route: str, out: dict, grid: dict, version: str, modules: list[str]) -> None:
    assert out["info"]["bundle_version"] == version and out["info"]["frame"] == "ref"
    Z, Y, X = grid["Z"], grid["Y"], grid["X"]
    if route == "map":
        assert out["observed"].shape == (Z, Y, X) and set(np.unique(out["observed"])) <= {0.0, 1.0}
        assert out["features"].shape[1:] == (Z, Y, X) and np.isfinite(out["features"]).all()
        if "occupancy" in modules:
            assert out["occupancy"].shape == (Z, Y, X) and out["heightmap"].shape == (Z, X)
            assert ((out["occupancy"] >= 0) & (out["occupancy"] <= 1)).all()
    elif route == "egomotion":
        T = out["cam0_T_cam1"]
        assert T.shape == (4, 4) and np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-3)
    elif route == "flow":
        assert out["flow"].shape == (3, Z, Y, X)
    else:
        assert out["frame"] == "ref" and out["bundle_version"] == version and out["boxes"].shape[1] == 7
        assert len(out["scores"]) == len(out["boxes"]) == len(out["velocities"])


@pytest.mark.parametrize("transport", ["rest-npz", "grpc"])
def test_every_route_answers_or_says_the_module_is_absent(server, rest, grpc_client, transport):
    from services.inference.client import GrpcClient, RestClient, ServiceCallError

    models = rest.models()
    f0, f1 = sample_frames(views=1, seed=0), sample_frames(views=1, seed=1)
    if transport == "grpc":
        client = grpc_client
    else:
        client = RestClient(server.url, encoding=transport.split("-")[1])
    try:
        for route in ROUTES:
            if route in models["routes"]:
                _check_answer(route, _call(client, route, f0, f1), models["grid"], models["bundle_version"],
                              models["modules"])
            else:
                with pytest.raises(ServiceCallError) as e:
                    _call(client, route, f0, f1)
                assert e.value.error == "module_unavailable" and route in e.value.detail
                assert e.value.status in (404, "UNIMPLEMENTED")
    finally:
        if not isinstance(client, GrpcClient):
            client.close()
    assert "map" in models["routes"]


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


def test_stream_answers_each_frame(server, grpc_client):
    from services.inference.client import ServiceCallError

    frames = [sample_frames(views=1, seed=s) for s in range(3)]
    for i, f in enumerate(frames):
        f.sequence = i
    if "moving_objects" not in grpc_client.models()["routes"]:
        with pytest.raises(ServiceCallError, match="module"):
            list(grpc_client.stream_moving_objects(frames))
        return
    out = list(grpc_client.stream_moving_objects(frames))
    assert [d["sequence"] for d in out] == [0, 1, 2] and len(out[0]["boxes"]) == 0
    assert all(d["frame"] == "ref" and d["camera_id"] == "cam0" for d in out)


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
