"""OpenAPI request examples: one complete, valid JSON request per POST route.

Swagger's "Try it out" sends these as they are, so each must be answered 200 by a server on any
bundle that has the route's modules (tests/integration/test_serve_openapi_examples.py POSTs every one
to a server on a tiny-preset bundle). They are built here rather than pasted as base64 so that the
values say what they are:

- one 6×18 view (the tiny preset's 1:3 aspect, 90° horizontal field of view: fx = fy = W/2, principal
  point at the image centre ((W−1)/2, (H−1)/2) under the pixel-centre convention);
- the camera looks along a flat ground 2 m below it: the top rows see sky (depth 0 = no return), the
  bottom rows see ground at depth 2·fy / (v − cy) metres along Z;
- `rgb` travels as a PNG, `depth` as a raw float32 array in metres, so both image encodings appear;
- the pair routes' second instant is the same view 0.2 s later (sequence 1) with the camera 0.5 m further
  forward (+Z), which leaves a flat ground's depth image unchanged.
Any image size is accepted: the map grid comes from the bundle, not from the images.
"""

from __future__ import annotations

import base64

import numpy as np

from services.inference import codecs

H, W = 6, 18
GROUND_BELOW_M = 2.0
FORWARD_STEP_M = 0.5
STEP_S = 0.2
_SKY = (135, 190, 235)
_GROUND = (110, 110, 105)


def _intrinsics() -> list[list[float]]:
    f = W / 2.0
    return [[f, 0.0, (W - 1) / 2.0, 0.0], [0.0, f, (H - 1) / 2.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def _pose(z_m: float) -> list[list[float]]:
    return [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, z_m], [0.0, 0.0, 0.0, 1.0]]


def _ground_depth() -> np.ndarray:
    """H×W float32 metres along Z of a flat ground GROUND_BELOW_M under the camera; 0 above the horizon."""
    fy, cy = W / 2.0, (H - 1) / 2.0
    below = np.arange(H, dtype=np.float64) - cy  # rows below the principal point look down
    rows = np.where(below > 0, GROUND_BELOW_M * fy / np.maximum(below, 1e-9), 0.0)
    return np.repeat(rows[:, None], W, axis=1).astype(np.float32)  # H×W


def _rgb(depth: np.ndarray) -> np.ndarray:
    """H×W×3 uint8: sky where there is no return, ground elsewhere."""
    return np.where(depth[..., None] > 0, np.array(_GROUND, np.uint8), np.array(_SKY, np.uint8))


def example_view(*, forward_m: float = 0.0, sequence: int = 0, timestamp: float = 0.0) -> dict:
    """A FrameJSON dict of the example view, its camera `forward_m` metres along world Z."""
    depth = _ground_depth()
    dtype, shape, data = codecs.array_to_bytes(depth)
    return {
        "rgb": {"png_b64": base64.b64encode(codecs.encode_png_rgb(_rgb(depth))).decode()},
        "depth": {"array": {"dtype": dtype, "shape": shape, "data_b64": base64.b64encode(data).decode()}},
        "pix_T_cam": _intrinsics(),
        "world_T_cam": _pose(forward_m),
        "camera_id": "front",
        "sequence": sequence,
        "timestamp": timestamp,
    }


def _openapi(summary: str, value: dict) -> dict:
    """An OpenAPI media-type `examples` map with one named example."""
    return {"tiny": {"summary": summary, "value": value}}


def _pair() -> dict:
    return {"views0": [example_view()],
            "views1": [example_view(forward_m=FORWARD_STEP_M, sequence=1, timestamp=STEP_S)]}


MAP = _openapi("one 6×18 view of flat ground (PNG rgb, float32 depth)",
               {"views": [example_view()], "features": False})
PAIR = _openapi("the same view twice, the camera 0.5 m further forward the second time", _pair())
FLOW = _openapi("the same view twice, the camera 0.5 m further forward the second time; stabilised with the poses",
                {**_pair(), "stabilise": "poses"})
DETECT = _openapi("one 6×18 view of flat ground", {"views": [example_view()], "min_score": 0.0})
MOVING_OBJECTS = _openapi("the same view twice, the camera 0.5 m further forward the second time",
                          {**_pair(), "min_score": -1.0})
RELOAD = _openapi("reload the bundle directory the server was started with", {})
