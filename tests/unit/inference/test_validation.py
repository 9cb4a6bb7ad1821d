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


def _far(z_m: float):
    T = np.eye(4)
    T[2, 3] = z_m
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
    # finite as float64 but inf once the model's float32 (a JSON body's 1e39 m translation answered null egomotion)
    ({"world_T_cam": _far(1e39)}, "views[1].world_T_cam", "float32"),
    ({"pix_T_cam": K * np.diag([1e39, 1, 1, 1])}, "views[1].pix_T_cam", "float32"),
    # positive as float64 but 0 or a denormal in float32: unprojection divided by ~0
    ({"pix_T_cam": K * np.diag([1e-46 / 32, 1, 1, 1])}, "views[1].pix_T_cam", "at least 0.001 px"),
    ({"pix_T_cam": K * np.diag([1, 1e-40 / 32, 1, 1])}, "views[1].pix_T_cam", "at least 0.001 px"),
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


def test_several_views_of_one_instant_each_need_their_pose():
    """A lone view may leave world_T_cam out (identity); fused views may not: the identity would be a guess."""
    assert not stack_views([_view(world_T_cam=None)], "views").posed
    assert stack_views([_view(), _view()], "views").posed
    with pytest.raises(InvalidInput) as e:
        stack_views([_view(), _view(world_T_cam=None)], "views0")
    assert e.value.field == "views0[1].world_T_cam"


def test_views_of_one_instant_were_captured_together():
    """Capture times of fused views: all given or none, and within MAX_VIEW_SKEW_S of each other (else a
    moving object would be fused twice); the instant's capture time is the latest."""
    from services.inference.validation import MAX_VIEW_SKEW_S

    together = stack_views([_view(capture_time=10.0), _view(capture_time=10.0 + 0.8 * MAX_VIEW_SKEW_S)], "views")
    assert together.capture_time == pytest.approx(10.0 + 0.8 * MAX_VIEW_SKEW_S)
    assert stack_views([_view(), _view()], "views").capture_time == 0.0
    with pytest.raises(InvalidInput) as e:
        stack_views([_view(capture_time=10.0), _view(), _view(capture_time=10.0)], "views0")
    assert e.value.field == "views0[1].capture_time" and "view 0" in str(e.value)
    with pytest.raises(InvalidInput) as e:  # view 0 was captured last, view 2 first
        stack_views([_view(capture_time=10.0 + 1.5 * MAX_VIEW_SKEW_S), _view(capture_time=10.01),
                     _view(capture_time=10.0)], "views1")
    assert e.value.field == "views1[0].capture_time" and "after view 2's" in str(e.value)


def _stamped(timestamp, sequence=0, capture_time=0.0):
    return stack_views([_view(timestamp=timestamp, sequence=sequence, capture_time=capture_time)], "v")


def test_pair_interval_reads_the_frames_clock():
    from services.inference.validation import pair_interval

    assert pair_interval(_stamped(0.0), _stamped(0.4), frame_dt=0.2, field1="views1") == pytest.approx(0.4)
    assert pair_interval(_stamped(0.0), _stamped(0.2), frame_dt=0.2, field1="views1") == pytest.approx(0.2)
    # no timestamps (both 0): sequence numbers × frame_dt, at least one interval
    assert pair_interval(_stamped(0.0, 3), _stamped(0.0, 5), frame_dt=0.1, field1="views1") == pytest.approx(0.2)
    assert pair_interval(_stamped(0.0, 3), _stamped(0.0, 3), frame_dt=0.1, field1="views1") == pytest.approx(0.1)
    for t0, t1 in ((5.0, 4.0), (5.0, 5.0), (5.0, 0.0)):
        with pytest.raises(InvalidInput) as e:
            pair_interval(_stamped(t0), _stamped(t1), frame_dt=0.2, field1="views1")
        assert e.value.field == "views1.timestamp"
    # advancing, but by too little to time motion over: velocities would overflow float32 (answered as null)
    with pytest.raises(InvalidInput, match="too short to time motion") as e:
        pair_interval(_stamped(1e-300), _stamped(2e-300), frame_dt=0.2, field1="views1")
    assert e.value.field == "views1.timestamp"
    with pytest.raises(InvalidInput, match="too short to time motion") as e:
        pair_interval(_stamped(0.0, capture_time=7.0), _stamped(0.0, capture_time=7.0 + 1e-9), frame_dt=0.2,
                      field1="views1")
    assert e.value.field == "views1.capture_time"
    assert pair_interval(_stamped(1.0), _stamped(1.001), frame_dt=0.2, field1="views1") == pytest.approx(0.001)


def test_pair_interval_prefers_the_capture_clock_when_both_frames_carry_it():
    """A recording replayed at 2 Hz was captured at 5 Hz: its frames are sent 0.5 s apart (timestamps)
    but the world in them moved 0.2 s (capture_time); motion is timed by the capture clock. One frame
    without a capture time: the timestamps decide, as before the field existed."""
    from services.inference.validation import pair_interval

    replayed0, replayed1 = _stamped(100.0, 0, capture_time=50.0), _stamped(100.5, 1, capture_time=50.2)
    assert pair_interval(replayed0, replayed1, frame_dt=0.1, field1="frame") == pytest.approx(0.2)
    assert pair_interval(_stamped(100.0, 0), replayed1, frame_dt=0.1, field1="frame") == pytest.approx(0.5)
    assert pair_interval(_stamped(0.0, 0, capture_time=50.0), _stamped(0.0, 4, capture_time=50.4), frame_dt=0.1,
                         field1="frame") == pytest.approx(0.4)  # no timestamps: the capture clock still decides
    with pytest.raises(InvalidInput) as e:  # timestamps advance, the capture clock does not
        pair_interval(replayed0, _stamped(100.5, 1, capture_time=50.0), frame_dt=0.1, field1="frame")
    assert e.value.field == "frame.capture_time"
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(InvalidInput) as e:
            _view(capture_time=bad)
        assert e.value.field.endswith(".capture_time")


def test_npz_bodies_refuse_unposed_views_and_bad_scalars():
    from services.inference.wire import views_from_npz

    V = np.zeros((2, 32, 64, 3), np.uint8)
    body = {"rgb0": V, "depth0": np.full((2, 32, 64), 3.0, np.float32), "pix_T_cam0": np.stack([K, K]).astype(np.float32)}
    with pytest.raises(InvalidInput) as e:
        views_from_npz(body, "0")
    assert e.value.field == "world_T_cam0"
    posed = {**body, "world_T_cam0": np.stack([_rot_y(0.1), _rot_y(0.2)]).astype(np.float32),
             "timestamp0": np.float64(1.5), "sequence0": np.uint64(7), "capture_time0": np.float64(0.4)}
    views = views_from_npz(posed, "0")
    assert views.timestamp == 1.5 and views.sequence == 7 and views.posed and views.capture_time == 0.4
    for name, value in (("timestamp0", np.float64(np.nan)), ("timestamp0", np.zeros(2)), ("sequence0", np.int64(-1)),
                        ("sequence0", np.float64(1.0)), ("capture_time0", np.float64(np.inf))):
        with pytest.raises(InvalidInput) as e:
            views_from_npz({**posed, name: value}, "0")
        assert e.value.field == name, (name, value)


def test_too_many_views_are_refused_before_any_is_decoded(monkeypatch):
    import services.inference.wire as wire
    from n3dmap.v1 import types_pb2

    decoded = []
    monkeypatch.setattr(wire, "make_view", lambda **kw: decoded.append(kw) or None)
    many = 20000   # one-pixel views: 2 kB compressed, seconds of validation on the event loop one by one
    body = {"rgb0": np.zeros((many, 1, 1, 3), np.uint8), "depth0": np.ones((many, 1, 1), np.float32),
            "pix_T_cam0": np.zeros((many, 4, 4), np.float32), "world_T_cam0": np.zeros((many, 4, 4), np.float32)}
    with pytest.raises(InvalidInput, match=f"need 1..16 views, got {many}") as e:
        wire.views_from_npz(body, "0")
    assert e.value.field == "views0"
    with pytest.raises(InvalidInput, match="need 1..16 views, got 17") as e:
        wire.views_from_proto([types_pb2.Frame() for _ in range(17)], "views0")
    assert e.value.field == "views0" and decoded == []
