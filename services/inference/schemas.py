"""JSON request/response schemas of the REST API (pydantic), with OpenAPI examples.

Arrays travel as `{dtype, shape, data_b64}` (little-endian, C order, base64); images as PNG in
base64 (`png_b64`) or as such an array; matrices as nested 4×4 lists. The whole-request examples of
each route are in services/inference/examples.py.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from services.inference.examples import example_view
from services.inference.validation import MAX_VIEWS

Matrix4 = list[list[float]]


class TensorJSON(BaseModel):
    """A raw array: numpy dtype name, shape, little-endian C-order bytes in base64."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"dtype": "float32", "shape": [1, 1],
                                                               "data_b64": "AACgQA=="}]})
    dtype: str = Field(max_length=16)
    shape: list[int] = Field(max_length=8)
    data_b64: str


class ImageJSON(BaseModel):
    """Exactly one of: a PNG (RGB 8-bit, or depth 16-bit millimetres) in base64, or a raw array."""

    png_b64: str | None = None
    array: TensorJSON | None = None


class FrameJSON(BaseModel):
    """One RGB-D view: rgb H×W×3 uint8; depth H×W metres (float32 array) or millimetres (uint16 PNG/array);
    intrinsics `pix_T_cam` 4×4; camera pose `world_T_cam` 4×4 rigid (identity when absent, which only a
    lone view of an instant may be: several views are fused by their poses)."""

    model_config = ConfigDict(json_schema_extra={"examples": [example_view()]})
    rgb: ImageJSON
    depth: ImageJSON
    pix_T_cam: Matrix4
    world_T_cam: Matrix4 | None = None
    camera_id: str = Field("", max_length=256)
    sequence: int = Field(0, ge=0, le=2**63 - 1)
    timestamp: float = Field(0.0, description="seconds on the source's clock; 0 = none given. Moving objects "
                                              "take their pair's interval from it unless both frames carry a "
                                              "capture_time")
    capture_time: float = Field(0.0, ge=0.0, description="when the scene was seen, seconds on the capture clock; "
                                                        "0 = none given. When both frames of a pair carry one, "
                                                        "their interval is its difference (a replayed recording)")


Views = list[FrameJSON]


class MapRequestJSON(BaseModel):
    views: Views = Field(min_length=1, max_length=MAX_VIEWS,
                         description="views of one instant; `ref` is the camera of views[0]")
    features: bool = Field(False, description="also return the F×Z×Y×X feature map")


class PairRequestJSON(BaseModel):
    views0: Views = Field(min_length=1, max_length=MAX_VIEWS, description="views at t0; `ref` = views0[0]")
    views1: Views = Field(min_length=1, max_length=MAX_VIEWS, description="views at t1, same layout")


Stabilise = Literal["egomotion", "poses", "none"]
STABILISE_DOC = ("how t1 is brought into ref0 before the flow compares it with t0: `egomotion` (the bundle's "
                 "estimate; needs an egomotion module), `poses` (the views' world_T_cam, which must then be given "
                 "for both instants; the default) or `none` (the flow carries the camera's own motion too)")


class FlowRequestJSON(PairRequestJSON):
    stabilise: Stabilise = Field("poses", description=STABILISE_DOC)


class DetectRequestJSON(BaseModel):
    views: Views = Field(min_length=1, max_length=MAX_VIEWS)
    min_score: float = Field(0.0, ge=0.0, le=1.0, description="objectness in [0, 1]")


class MovingObjectsRequestJSON(BaseModel):
    """Velocities are m/s over the frames' clock: views1's capture_time minus views0's when both carry one,
    else views1's timestamp minus views0's (it must be later); when both are 0, (views1 sequence − views0
    sequence, at least 1) × the server's --frame-dt. A bundle without an egomotion module stabilises with the
    poses, which must then be given."""

    views0: Views = Field(min_length=1, max_length=MAX_VIEWS, description="views at t0; `ref` = views0[0]")
    views1: Views = Field(min_length=1, max_length=MAX_VIEWS, description="views at t1, same layout")
    min_score: float = Field(-1.0, ge=-1.0, le=1.0, description="center-surround saliency in [−1, 1]")


class ReloadRequestJSON(BaseModel):
    bundle: str | None = Field(None, description="bundle directory on the server; default: reload the current one")


class ResponseInfoJSON(BaseModel):
    bundle_version: str
    frame: str = Field(description="frame of every pose, volume and box of the response ('ref')")
    model_s: float
    queue_s: float
    batch_size: int


class GridJSON(BaseModel):
    xmin: float
    xmax: float
    ymin: float
    ymax: float
    zmin: float
    zmax: float
    Z: int
    Y: int
    X: int


class MapResponseJSON(BaseModel):
    info: ResponseInfoJSON
    grid: GridJSON
    observed: TensorJSON = Field(description="Z×Y×X float32 in {0, 1}: inside some view's frustum")
    occupancy: TensorJSON | None = Field(None, description="Z×Y×X float32 in [0, 1] (bundles with an occupancy head)")
    heightmap: TensorJSON | None = Field(None, description="Z×X float32 metres above the grid floor (ref y = ymax) "
                                                          "of the highest occupied voxel's top face; 0 = empty column")
    features: TensorJSON | None = Field(None, description="F×Z×Y×X float32, when asked")


class EgomotionResponseJSON(BaseModel):
    info: ResponseInfoJSON
    cam0_T_cam1: Matrix4


class FlowResponseJSON(BaseModel):
    info: ResponseInfoJSON
    grid: GridJSON
    flow: TensorJSON = Field(description="3×Z×Y×X float32, voxel units, channels (x, y, z), t0 -> t1")


class Box3DJSON(BaseModel):
    x: float
    y: float
    z: float
    lx: float
    ly: float
    lz: float
    yaw: float
    frame: str
    score: float
    label: str
    vx: float = 0.0
    vy: float = 0.0
    vz: float = 0.0


class DetectionsResponseJSON(BaseModel):
    info: ResponseInfoJSON
    frame: str = Field(description="frame of every box")
    bundle_version: str
    camera_id: str
    sequence: int
    source_timestamp: float
    boxes: list[Box3DJSON]


class ModelsResponseJSON(BaseModel):
    bundle_version: str
    bundle_path: str
    preset: str
    modules: list[str]
    routes: list[str]
    grid: GridJSON
    device: str
    loaded_at: float
    last_reload_error: str | None
    meta_json: str


class ErrorJSON(BaseModel):
    error: str = Field(description="invalid_input | module_unavailable | overloaded | timeout | not_ready | unauthorized")
    detail: str
    field: str | None = None
