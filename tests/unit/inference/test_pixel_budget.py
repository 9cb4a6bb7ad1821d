"""A request's pixel budget (codecs.PixelBudget): every rgb and depth image of a request is charged before it is
decoded — a PNG from its header, an array from its declared shape — over all its views and both instants of a
pair, and the first image past the budget is refused naming it, with nothing of it decoded."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from n3dmap.v1 import types_pb2
from services.cli.serve import MAX_REQUEST_PIXELS as CLI_DEFAULT
from services.inference import codecs, wire
from services.inference.errors import InvalidInput
from services.inference.schemas import FrameJSON

H, W = 6, 8


def K() -> np.ndarray:
    return np.array([[4, 0, 3.5, 0], [0, 4, 2.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)


def rgb(h: int = H, w: int = W) -> np.ndarray:
    return np.full((h, w, 3), 100, np.uint8)


def depth_m(h: int = H, w: int = W) -> np.ndarray:
    return np.full((h, w), 2.0, np.float32)


def json_frame(*, png: bool, h: int = H, w: int = W) -> FrameJSON:
    if png:
        rgb_json = {"png_b64": base64.b64encode(codecs.encode_png_rgb(rgb(h, w))).decode()}
        depth_json = {"png_b64": base64.b64encode(codecs.encode_png_depth(depth_m(h, w))).decode()}
    else:
        rgb_json = {"array": {"dtype": "uint8", "shape": [h, w, 3], "data_b64": codecs.b64encode(rgb(h, w).tobytes())}}
        depth_json = {"array": {"dtype": "float32", "shape": [h, w],
                                "data_b64": codecs.b64encode(depth_m(h, w).tobytes())}}
    return FrameJSON.model_validate({"rgb": rgb_json, "depth": depth_json, "pix_T_cam": K().tolist(),
                                     "world_T_cam": np.eye(4).tolist()})


def proto_frame(*, png: bool) -> types_pb2.Frame:
    def image(arr, encode):
        return types_pb2.Image(png=encode(arr)) if png else types_pb2.Image(array=codecs.numpy_to_tensor(arr))
    return types_pb2.Frame(rgb=image(rgb(), codecs.encode_png_rgb), depth=image(depth_m(), codecs.encode_png_depth),
                           pix_T_cam=codecs.numpy_to_tensor(K().astype(np.float32)),
                           world_T_cam=codecs.numpy_to_tensor(np.eye(4, dtype=np.float32)))


def test_the_budget_is_spent_image_by_image_and_refuses_the_first_past_it():
    budget = codecs.PixelBudget(100)
    budget.take(60, "a")
    budget.take(40, "b")               # exactly the budget: taken
    assert budget.left == 0
    with pytest.raises(InvalidInput) as e:
        budget.take(1, "c")
    assert e.value.field == "c" and "budget of 100 pixels" in str(e.value) and "100 used" in str(e.value)
    assert budget.left == 0            # a refused image takes nothing


def test_image_pixels_of_a_shape():
    assert codecs.image_pixels((6, 8)) == 48 and codecs.image_pixels((6, 8, 3)) == 48
    assert codecs.image_pixels([5]) == 5 and codecs.image_pixels((2, 3, 4, 5)) == 120   # refused later as a shape


def test_the_cli_default_is_the_service_default():
    assert CLI_DEFAULT == codecs.MAX_REQUEST_PIXELS


def test_a_png_is_charged_from_its_header_before_it_is_decoded(monkeypatch):
    png = codecs.encode_png_rgb(rgb())
    budget = codecs.PixelBudget(H * W - 1)
    loaded = []
    monkeypatch.setattr(codecs.PILImage.Image, "load", lambda self: loaded.append(1))
    with pytest.raises(InvalidInput) as e:
        codecs.decode_png_rgb(png, "views[0].rgb.png_b64", budget)
    assert e.value.field == "views[0].rgb.png_b64" and not loaded   # refused from the header: no pixel decoded
    assert budget.left == H * W - 1


@pytest.mark.parametrize("png", [True, False], ids=["png", "array"])
def test_json_views_charge_rgb_and_depth_and_a_pair_shares_one_budget(png):
    per_view = 2 * H * W                                  # rgb and depth each counted
    budget = codecs.PixelBudget(3 * per_view)
    views0 = wire.views_from_json([json_frame(png=png), json_frame(png=png)], "views0", budget)
    assert views0.rgb.shape[0] == 2 and budget.left == per_view
    wire.views_from_json([json_frame(png=png)], "views1", budget)    # the pair's last view: exactly the budget
    assert budget.left == 0
    with pytest.raises(InvalidInput) as e:
        wire.views_from_json([json_frame(png=png)], "views1", budget)
    assert e.value.field == ("views1[0].rgb.png_b64" if png else "views1[0].rgb.array")


def test_json_depth_is_charged_on_its_own_so_a_large_depth_behind_a_small_rgb_is_refused():
    frame = json_frame(png=True)
    big = json_frame(png=True, h=60, w=80)
    frame.depth = big.depth                                 # a 60×80 depth behind a 6×8 rgb
    with pytest.raises(InvalidInput) as e:
        wire.views_from_json([frame], "views", codecs.PixelBudget(H * W + 60 * 80 - 1))
    assert e.value.field == "views[0].depth.png_b64"


def test_npz_views_charge_whole_arrays():
    arrays = {"rgb0": np.stack([rgb()] * 2), "depth0": np.stack([depth_m()] * 2), "pix_T_cam0": np.stack([K()] * 2),
              "world_T_cam0": np.stack([np.eye(4)] * 2)}
    budget = codecs.PixelBudget(4 * H * W)
    wire.views_from_npz(arrays, "0", budget)
    assert budget.left == 0
    with pytest.raises(InvalidInput) as e:
        wire.views_from_npz(arrays, "0", codecs.PixelBudget(4 * H * W - 1))
    assert e.value.field == "depth0"     # rgb0 took 2·H·W, depth0's 2·H·W is one over


@pytest.mark.parametrize("png", [True, False], ids=["png", "array"])
def test_proto_views_are_charged(png):
    frames = [proto_frame(png=png), proto_frame(png=png)]
    budget = codecs.PixelBudget(4 * H * W)
    wire.views_from_proto(frames, "views0", budget)
    assert budget.left == 0
    with pytest.raises(InvalidInput) as e:
        wire.views_from_proto(frames, "views0", codecs.PixelBudget(3 * H * W))
    assert e.value.field == ("views0[1].depth.png" if png else "views0[1].depth.array")


def test_without_a_budget_each_call_has_the_default_one():
    views = wire.views_from_proto([proto_frame(png=False)], "views")
    assert views.rgb.shape == (1, H, W, 3)
