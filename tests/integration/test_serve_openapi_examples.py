"""The OpenAPI request examples of a real `n3dmap serve` on a tiny bundle: every POST route has one,
and each is answered 200 with a real result. Swagger's "Try it out" sends them as they are."""

from __future__ import annotations

import base64

import httpx
import numpy as np
import pytest

from tests.integration.serve_support import ServerProcess, make_bundle

pytestmark = pytest.mark.integration

INFERENCE_ROUTES = {"/v1/map", "/v1/egomotion", "/v1/flow", "/v1/detect", "/v1/moving-objects"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serve_examples")
    bundle = make_bundle(tmp / "bundle")  # every module, so every inference route is served
    with ServerProcess(bundle, log_path=tmp / "server.log") as s:
        yield s


@pytest.fixture(scope="module")
def spec(server) -> dict:
    return httpx.get(server.url + "/openapi.json").json()


def post_examples(spec: dict) -> dict[str, dict[str, dict]]:
    """{path: {example name: JSON request body}} for every POST operation; {} where it has none."""
    out = {}
    for path, operations in spec["paths"].items():
        if "post" in operations:
            media = operations["post"].get("requestBody", {}).get("content", {}).get("application/json", {})
            out[path] = {name: example["value"] for name, example in media.get("examples", {}).items()}
    return out


def _array(tensor_json: dict) -> np.ndarray:
    data = base64.b64decode(tensor_json["data_b64"])
    return np.frombuffer(data, dtype=np.dtype(tensor_json["dtype"]).newbyteorder("<")).reshape(tensor_json["shape"])


def test_every_post_route_has_a_json_request_example(spec):
    examples = post_examples(spec)
    assert set(examples) >= INFERENCE_ROUTES | {"/v1/admin/reload"}
    missing = sorted(path for path, named in examples.items() if not named)
    assert not missing, f"POST routes without an OpenAPI request example: {missing}"


def test_every_request_example_is_answered_200(server, spec):
    grid = httpx.get(server.url + "/v1/models").json()["grid"]
    Z, Y, X = grid["Z"], grid["Y"], grid["X"]
    answered = set()
    for path, named in post_examples(spec).items():
        for name, body in named.items():
            r = httpx.post(server.url + path, json=body, timeout=60)
            assert r.status_code == 200, (path, name, r.status_code, r.text[:500])
            out = r.json()
            answered.add(path)
            if path in INFERENCE_ROUTES:
                assert out["info"]["frame"] == "ref"
            if path == "/v1/map":
                observed = _array(out["observed"])
                assert observed.shape == (Z, Y, X) and observed.sum() > 0  # the view sees part of the grid
                assert _array(out["occupancy"]).shape == (Z, Y, X)
            elif path == "/v1/egomotion":
                T = np.array(out["cam0_T_cam1"])
                assert T.shape == (4, 4) and np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-3)
            elif path == "/v1/flow":
                assert _array(out["flow"]).shape == (3, Z, Y, X)
            elif path in ("/v1/detect", "/v1/moving-objects"):
                assert out["camera_id"] == "front" and isinstance(out["boxes"], list)
            elif path == "/v1/admin/reload":
                assert out["preset"] == "tiny" and set(out["routes"]) >= {"map", "moving_objects"}
    assert answered >= INFERENCE_ROUTES | {"/v1/admin/reload"}
