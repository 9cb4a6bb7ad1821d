"""A fault of the server (a model that raises) is answered as every other REST error is: JSON
`{error: "internal", detail, field}` with status 500, counted in the request metrics — not Starlette's
plain-text "Internal Server Error". The app is the real one over a real runtime and bundle, driven in
process; the fault is a mapper whose encoding raises, as a CUDA out-of-memory would.
"""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from services.inference import examples
from services.inference.rest import create_app
from services.inference.runtime import Runtime, RuntimeConfig
from tests.integration.serve_support import make_bundle


@pytest.fixture(scope="module")
def runtime(tmp_path_factory):
    bundle = make_bundle(tmp_path_factory.mktemp("bundle"), kinds=("mapper", "occupancy"))
    return Runtime(RuntimeConfig(bundle_dir=str(bundle), device="cpu"))


def test_a_model_fault_is_a_json_500_counted_in_the_metrics(runtime):
    app = create_app(runtime)
    body = examples.MAP["tiny"]["value"]
    with TestClient(app, raise_server_exceptions=False) as client:
        healthy = client.post("/v1/map", json=body)
        assert healthy.status_code == 200, healthy.text

        def out_of_memory(*args, **kwargs):
            raise RuntimeError("CUDA out of memory (injected)")

        mapper = runtime.bundle.modules["mapper"]
        mapper.encode_views = out_of_memory   # instance attribute, found before the method (core/pipeline/map.py)
        try:
            r = client.post("/v1/map", json=body)
        finally:
            del mapper.encode_views
        assert r.status_code == 500
        assert r.headers["content-type"].startswith("application/json")
        assert r.json() == {"error": "internal", "detail": "RuntimeError: CUDA out of memory (injected)",
                            "field": None}
        metrics = client.get("/metrics").text
        counted = [line for line in metrics.splitlines()
                   if line.startswith("n3dmap_requests_total") and 'status="500"' in line and "/v1/map" in line]
        assert counted and float(counted[0].rsplit(" ", 1)[1]) == 1.0, metrics
        assert client.post("/v1/map", json=body).status_code == 200   # the fault passed; the server serves on
