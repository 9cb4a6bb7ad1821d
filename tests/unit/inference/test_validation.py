"""Each validation rule refuses what it should, naming the field, and accepts good views."""

import numpy as np
import pytest

from services.inference.errors import InvalidInput
from services.inference.validation import check_pair, make_view, stack_views

K = np.array([[50.0, 0, 31.5, 0], [0, 50.0, 15.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def _rot_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [1.0, -0.5, 2.0]
    return T


def _view(**over):
    args = dict(rgb=np.zeros((32, 64, 3), np.uint8), depth=np.full((32, 64), 3.0, np.float32), pix_T_cam=K,
                world_T_cam=_rot_y(0.3), field="views[1]")
    args.update(over)
    return make_view(**args)


def test_good_view_passes_and_converts():
    v = _view(depth=np.full((32, 64), 3000, np.uint16))
    assert v.depth.dtype == np.float32 and np.allclose(v.depth, 3.0)
    assert v.pix_T_cam.dtype == np.float32 and np.allclose(v.world_T_cam, _rot_y(0.3))
    assert np.array_equal(_view(world_T_cam=None).world_T_cam, np.eye(4))


def _nonrigid():
    T = _rot_y(0.3)
    T[:3, :3] *= 1.1
    return T


def _reflection():
    T = np.eye(4)
    T[0, 0] = -1
    return T


@pytest.mark.parametrize("over,field,needle", [
    ({"rgb": np.zeros((32, 64, 3), np.float32)}, "views[1].rgb", "uint8"),
    ({"rgb": np.zeros((32, 64), np.uint8)}, "views[1].rgb", "H×W×3"),
    ({"depth": np.zeros((32, 64), np.int64)}, "views[1].depth", "float32"),
    ({"depth": np.zeros((32, 65), np.float32)}, "views[1].depth", "differs"),
    ({"depth": np.full((32, 64), np.nan, np.float32)}, "views[1].depth", "non-finite"),
    ({"depth": np.full((32, 64), -1.0, np.float32)}, "views[1].depth", "[0,"),
    ({"pix_T_cam": K * np.diag([-1, 1, 1, 1])}, "views[1].pix_T_cam", "positive"),
    ({"pix_T_cam": np.eye(3)}, "views[1].pix_T_cam", "4×4"),
    ({"pix_T_cam": np.where(np.eye(4) > 0, np.inf, 0)}, "views[1].pix_T_cam", "non-finite"),
    ({"world_T_cam": _nonrigid()}, "views[1].world_T_cam", "rigid"),
    ({"world_T_cam": _reflection()}, "views[1].world_T_cam", "rigid"),
])
def test_bad_views_name_the_field(over, field, needle):
    with pytest.raises(InvalidInput) as e:
        _view(**over)
    assert e.value.field == field and needle in str(e.value)


def test_stack_and_pair_rules():
    views = stack_views([_view(), _view()], "views")
    assert views.shape_key == (2, 32, 64) and views.rgb.shape == (2, 32, 64, 3)
    with pytest.raises(InvalidInput, match="1..16"):
        stack_views([], "views")
    small = _view(rgb=np.zeros((16, 64, 3), np.uint8), depth=np.ones((16, 64), np.float32))
    with pytest.raises(InvalidInput) as e:
        stack_views([_view(), small], "views0")
    assert e.value.field == "views0[1]"
    with pytest.raises(InvalidInput) as e:
        check_pair(views, stack_views([_view()], "views1"), "views1")
    assert e.value.field == "views1"
