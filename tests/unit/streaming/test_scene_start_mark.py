"""The pieces the bridge uses to carry a dropped frame's scene_start mark: RuntimeProcessor reads the flag
from a payload without validating it, and `mark_scene_start` sets it on a decoded View (a frozen
dataclass, so a copy) as on any other decoded frame. The bridge's use of them is tested over real zenoh in
test_bridge_accounting.py."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from n3dmap.v1 import types_pb2
from services.inference.validation import View
from services.streaming.bridge import mark_scene_start
from services.streaming.processor import RuntimeProcessor


def test_the_flag_is_read_from_the_payload_and_garbage_starts_nothing():
    assert RuntimeProcessor.starts_scene(types_pb2.Frame(camera_id="cam0", sequence=3, scene_start=True)
                                         .SerializeToString())
    assert not RuntimeProcessor.starts_scene(types_pb2.Frame(camera_id="cam0", sequence=3).SerializeToString())
    assert not RuntimeProcessor.starts_scene(b"\xff\xff\xff not a frame")


def test_a_view_is_copied_with_the_mark_and_other_frames_are_marked_in_place():
    view = View(rgb=np.zeros((2, 3, 3), np.uint8), depth=np.ones((2, 3), np.float32),
                pix_T_cam=np.eye(4, dtype=np.float32), world_T_cam=np.eye(4, dtype=np.float32), sequence=5)
    marked = mark_scene_start(view)
    assert marked.scene_start and not view.scene_start and marked.sequence == 5 and marked.rgb is view.rgb
    other = SimpleNamespace(sequence=1, scene_start=False)
    assert mark_scene_start(other) is other and other.scene_start
