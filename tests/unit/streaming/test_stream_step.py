"""core.pipeline.moving_step and the bridge's RuntimeProcessor give what the inference routes give.

The reference is the slow, obvious path the bridge used before: for every pair, the runtime's
`egomotion` route and its `moving_objects` route (which estimates egomotion again and encodes both
frames from scratch). The fast path reuses the previous frame's encoding (made during idle time by
`prepare`, or by the previous step) and runs egomotion once. Modules are freshly initialised with
small random flow weights (an untrained flow module predicts exactly zero), so flow, stabilisation
and boxes all carry numbers that would differ if a cached tensor were stale or misplaced.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.bundle import Bundle, save_bundle
from core.pipeline import encode_previous, moving_objects, moving_step
from core.pipeline.egomotion import estimate_egomotion
from core.pipeline.moving import MovingObjectsConfig
from core.presets import TINY
from core.tasks.egomotion import EgomotionTask
from core.tasks.flow import FlowTask
from core.tasks.occupancy import OccupancyTask
from n3dmap.v1 import inference_pb2, types_pb2
from services.inference import codecs
from services.inference.routes import MovingInput, PairInput
from services.inference.runtime import Runtime, RuntimeConfig
from services.inference.validation import stack_views
from services.streaming.bridge import CameraState
from services.streaming.camera import encode_frame
from services.streaming.processor import RuntimeProcessor, views_tensors
from services.streaming.sources import synthetic_frames

ATOL = 1e-5


@pytest.fixture(autouse=True)
def _one_torch_thread(one_torch_thread):
    """Every test here runs on one torch thread (tests/conftest.py)."""


def fresh_modules(flow_inputs: str = "volume") -> dict:
    torch.manual_seed(0)
    flow_task = FlowTask.from_preset(TINY, inputs=flow_inputs)
    with torch.no_grad():
        for p in flow_task.flow.parameters():
            if p.dim() > 1 and not p.any():
                p.normal_(std=0.3)  # flows of ~0.5 voxels: above the 0.2-voxel speed threshold in places
    torch.manual_seed(1)  # the occupancy head's draw must not depend on how many numbers the flow module took
    occupancy = OccupancyTask.from_preset(TINY).occupancy
    with torch.no_grad():  # a spread of P(occupied) around 0.5, so the occupancy gate keeps some flow
        occupancy.conv.weight.normal_(std=2.0)
        occupancy.conv.bias.fill_(0.0)
    egomotion = EgomotionTask.from_preset(TINY).egomotion
    with torch.no_grad():  # its zero-initialised residual layers too, so the estimate is no identity
        for p in egomotion.parameters():
            if not p.any():
                p.normal_(std=0.05)
    return {"mapper": flow_task.mapper, "flow": flow_task.flow, "occupancy": occupancy, "egomotion": egomotion}


@pytest.fixture(scope="module", params=["volume", "features"])
def bundle_dir(tmp_path_factory, request):
    """A bundle whose flow module compares input volumes (the default) or the mapper's maps."""
    out = tmp_path_factory.mktemp(f"stream_bundle_{request.param}")
    save_bundle(out, modules=fresh_modules(request.param), preset=TINY, provenance={"test": "stream_step"},
                metrics={})
    return out


@pytest.fixture(scope="module")
def frames():
    """5 consecutive frames of one scene with a moving ego (so egomotion is not the identity)."""
    source = synthetic_frames(preset_name="tiny", seed=3, frames_per_episode=5, moving_ego=True)
    return [next(source) for _ in range(5)]


def decoded(processor, frames):
    return [processor.decode(encode_frame(f, camera_id="c", sequence=i, timestamp=1000.0 + i))
            for i, f in enumerate(frames)]


def test_moving_step_equals_moving_objects_and_egomotion(bundle_dir, frames):
    bundle = Runtime(RuntimeConfig(bundle_dir=str(bundle_dir), device="cpu")).bundle
    processor = RuntimeProcessor.__new__(RuntimeProcessor)  # decode() needs no runtime
    views = [stack_views([v], "v") for v in decoded(processor, frames)]
    tensors = [views_tensors(v, torch.device("cpu")) for v in views]
    previous = None
    for t in range(1, len(frames)):
        pair = {**{f"{k}0": v for k, v in tensors[t - 1].items()}, **{f"{k}1": v for k, v in tensors[t].items()}}
        if t == 3:  # the idle-time path: the encoding made ahead of the step
            previous = encode_previous(bundle, **tensors[t - 1], cached=previous)
        timings: dict = {}
        fast = moving_step(bundle, **pair, previous=previous, timings=timings)
        slow = moving_objects(bundle, **pair)
        ego = estimate_egomotion(bundle, **pair)
        assert not torch.allclose(ego["cam0_T_cam1"], torch.eye(4), atol=1e-3)  # stabilisation matters
        assert slow["flow"].abs().max() > 0.2 and (slow["flow"] == 0).any()  # flow, gated in places
        assert slow["valid"].any()  # boxes to compare
        for key in ("flow", "ref0_T_ref1", "boxes", "scores", "valid", "velocities"):
            assert fast[key].shape == slow[key].shape, key
            assert torch.allclose(fast[key].float(), slow[key].float(), atol=ATOL), key
        assert torch.allclose(fast["cam0_T_cam1"], ego["cam0_T_cam1"], atol=ATOL)
        assert {"ego_volume", "egomotion", "flow", "boxes"} <= set(timings)
        # frame 1's map is made only for a flow module that compares maps
        assert ("map_current" in timings) == (bundle.modules["flow"].inputs != "volume")
        assert ("map_previous" in timings) == (previous is None or previous.features is None)
        previous = fast["current"]
        assert previous.ego_volume is not None and previous.features is None


def test_moving_step_with_poses_and_without_egomotion(bundle_dir, frames):
    full = Runtime(RuntimeConfig(bundle_dir=str(bundle_dir), device="cpu")).bundle
    bundle = Bundle(preset=TINY, modules={k: m for k, m in full.modules.items() if k != "egomotion"})
    tensors = [views_tensors(stack_views([v], "v"), torch.device("cpu"))
               for v in decoded(RuntimeProcessor.__new__(RuntimeProcessor), frames[:2])]
    pair = {**{f"{k}0": v for k, v in tensors[0].items()}, **{f"{k}1": v for k, v in tensors[1].items()}}
    fast, slow = moving_step(bundle, **pair), moving_objects(bundle, **pair)
    assert "cam0_T_cam1" not in fast and fast["current"].ego_volume is None
    for key in ("flow", "ref0_T_ref1", "boxes", "scores"):
        assert torch.allclose(fast[key], slow[key], atol=ATOL), key


def test_processor_answers_equal_the_routes(bundle_dir, frames):
    """The bridge's processor (cache + idle preparation) against the two route calls per pair."""
    runtime = Runtime(RuntimeConfig(bundle_dir=str(bundle_dir), device="cpu"))
    processor = RuntimeProcessor(runtime, min_score=-1.0)
    state = CameraState()
    views = decoded(processor, frames)
    boxes_seen = 0
    for t, frame in enumerate(views):
        outputs = processor.process("c", state, frame)
        got = types_pb2.Detections.FromString(outputs.moving_objects)
        assert got.sequence == t and got.source_timestamp == pytest.approx(1000.0 + t) and got.frame == "ref"
        if t == 0:
            assert outputs.egomotion is None and len(got.boxes) == 0
        else:
            v0, v1 = stack_views([views[t - 1]], "a"), stack_views([frame], "b")
            (ego,) = runtime.infer_sync("egomotion", [PairInput(views0=v0, views1=v1)])
            (moving,) = runtime.infer_sync("moving_objects", [MovingInput(views0=v0, views1=v1, min_score=-1.0)])
            sent = inference_pb2.EgomotionResponse.FromString(outputs.egomotion)
            np.testing.assert_allclose(codecs.tensor_to_numpy(sent.cam0_T_cam1, "cam0_T_cam1"), ego.cam0_T_cam1,
                                       atol=ATOL)
            assert len(got.boxes) == len(moving.scores)
            boxes_seen += len(got.boxes)
            for box, ref_box, score in zip(got.boxes, moving.boxes, moving.scores):
                np.testing.assert_allclose([box.x, box.y, box.z, box.lx, box.ly, box.lz, box.yaw], ref_box, atol=1e-4)
                assert box.score == pytest.approx(float(score), abs=1e-5)
        state.previous, state.last_sequence = frame, t
        if t % 2 == 0:  # half the steps find the previous frame encoded ahead, half encode it themselves
            processor.prepare("c", state)
            assert state.extra["encoding"].features is not None and state.extra["sequence"] == t
    assert boxes_seen > 0  # the box comparison compared something
    stats = processor.stats()
    assert stats["step_total"]["count"] == len(frames) - 1
    assert stats["idle_map_previous"]["count"] >= 2


def test_a_pair_across_dropped_frames_spans_their_intervals(bundle_dir, frames):
    """Frames 0 -> 2 (1 dropped) at 0.25 s per frame: velocities and the speed threshold use 0.5 s, i.e.
    they equal the pipeline run with dt = 0.5 (the velocities of a one-interval pair would be 2× too fast)."""
    runtime = Runtime(RuntimeConfig(bundle_dir=str(bundle_dir), device="cpu"))
    processor = RuntimeProcessor(runtime, min_score=-1.0, frame_dt=0.25)
    views = decoded(processor, frames)
    state = CameraState()
    processor.process("c", state, views[0])
    state.previous, state.last_sequence = views[0], 0
    got = types_pb2.Detections.FromString(processor.process("c", state, views[2]).moving_objects)
    tensors = [views_tensors(stack_views([v], "v"), torch.device("cpu")) for v in (views[0], views[2])]
    pair = {**{f"{k}0": v for k, v in tensors[0].items()}, **{f"{k}1": v for k, v in tensors[1].items()}}
    slow = moving_objects(runtime.bundle, **pair, config=MovingObjectsConfig(dt=0.5))
    keep = slow["valid"][0]
    assert keep.any() and len(got.boxes) == int(keep.sum())
    order = torch.argsort(-slow["scores"][0][keep], stable=True)
    for box, velocity in zip(got.boxes, slow["velocities"][0][keep][order]):
        np.testing.assert_allclose([box.vx, box.vy, box.vz], velocity.numpy(), atol=1e-4)
    assert processor.pair_dt(0, 2) == 0.5 and processor.pair_dt(4, 5) == 0.25
    with pytest.raises(ValueError, match="frame_dt"):
        RuntimeProcessor(runtime, frame_dt=0.0)


def test_cache_is_keyed_by_sequence(bundle_dir, frames):
    """A stale cache (another frame's encoding) is never used: the step recomputes instead."""
    runtime = Runtime(RuntimeConfig(bundle_dir=str(bundle_dir), device="cpu"))
    processor = RuntimeProcessor(runtime, min_score=-1.0)
    views = decoded(processor, frames)
    state = CameraState()
    processor.process("c", state, views[0])
    state.previous, state.last_sequence = views[0], 0
    processor.prepare("c", state)
    stale = state.extra["encoding"]
    # frame 2 follows frame 1, but the cache still holds frame 0's encoding under sequence 0
    state.previous, state.last_sequence = views[1], 1
    processor.process("c", state, views[2])
    assert processor.stats()["map_previous"]["count"] == 1  # frame 1 was encoded, frame 0's cache ignored
    assert state.extra["sequence"] == 2 and state.extra["encoding"] is not stale


def test_bridge_frame_dt_default_is_the_pipelines():
    from core.pipeline.moving import DEFAULT_DT
    from services.cli.stream import DEFAULT_FRAME_DT

    assert DEFAULT_FRAME_DT == DEFAULT_DT
