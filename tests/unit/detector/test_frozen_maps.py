"""The frozen mapper's map cache: each example's map as the mapper computes it alone, reused by input digest,
emptied when the weights change, bounded in bytes; and the detector task's frozen training through it."""

from __future__ import annotations

import pytest
import torch

from core.data.batch import records_to_batch
from core.models.latent_map import Mapper
from core.presets import TINY
from core.synthetic import generate_record
from core.tasks import build_task
from core.tasks.frozen_maps import FrozenMapCache
from core.tasks.poses import cam_T_ref


@pytest.fixture(scope="module")
def batch():
    return records_to_batch([generate_record(TINY, seed=s, num_frames=2, moving_ego=True) for s in (3, 4, 5)])


def _inputs(batch, t=0):
    """The Mapper's inputs of time t: rgb B×V×3×H×W, depth B×V×H×W, pix_T_cam, cam_T_ref B×V×4×4."""
    return batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"], cam_T_ref(batch, t, t)


def _mapper(seed=0):
    torch.manual_seed(seed)
    mapper = Mapper(grid=TINY.grid, width=TINY.encoder_width, feature_dim=TINY.feature_dim,
                    full_res=TINY.encoder_full_res)
    return mapper.eval().requires_grad_(False)


class _Counting:
    """Counts the mapper's forward calls and the examples they took."""

    def __init__(self, mapper):
        self.calls, self.examples = 0, 0
        mapper.register_forward_hook(self._hook)

    def _hook(self, module, args, output):
        self.calls += 1
        self.examples += args[0].shape[0]


def test_maps_are_each_example_alone_and_reused_by_inputs(batch):
    mapper = _mapper()
    counting = _Counting(mapper)
    rgb, depth, K, poses = _inputs(batch)
    with torch.no_grad():  # the slow, obvious reference: one example at a time, and the whole batch at once
        alone = torch.cat([mapper(rgb[b:b + 1], depth[b:b + 1], K[b:b + 1], poses[b:b + 1]) for b in range(3)])
        together = mapper(rgb, depth, K, poses)
    counting.calls = counting.examples = 0
    cache = FrozenMapCache(max_bytes=1 << 30)
    got = cache.maps(mapper, rgb, depth, K, poses)
    assert torch.equal(got, alone) and not got.requires_grad
    torch.testing.assert_close(got, together, atol=1e-5, rtol=1e-5)
    assert (counting.examples, cache.misses, cache.hits, len(cache)) == (3, 3, 0, 3)
    order = torch.tensor([2, 0])  # another batch of the same examples: all from the cache, in its order
    again = cache.maps(mapper, rgb[order], depth[order], K[order], poses[order])
    assert torch.equal(again, alone[order]) and counting.examples == 3 and cache.hits == 2
    later = _inputs(batch, t=1)   # another time step: other inputs, other maps
    cache.maps(mapper, *(x[:1] for x in later))
    assert counting.examples == 4 and len(cache) == 4


def test_changed_weights_empty_the_cache(batch):
    mapper = _mapper()
    inputs = [x[:1] for x in _inputs(batch)]
    cache = FrozenMapCache(max_bytes=1 << 30)
    before = cache.maps(mapper, *inputs)
    mapper.load_state_dict(_mapper(seed=1).state_dict())   # in place: the same tensors, new versions
    after = cache.maps(mapper, *inputs)
    with torch.no_grad():
        want = mapper(*inputs)
    assert torch.equal(after, want) and not torch.equal(after, before) and cache.misses == 2 and len(cache) == 1


def test_cpu_autocast_empties_the_cache(batch):
    """Maps kept in fp32 are not returned under CPU bf16 autocast (`train --precision bf16` on a CPU), nor the
    reverse: the reference is the mapper run directly in each state."""
    mapper = _mapper()
    inputs = [x[:1] for x in _inputs(batch)]
    cache = FrozenMapCache(max_bytes=1 << 30)
    plain = cache.maps(mapper, *inputs)
    with torch.autocast("cpu", dtype=torch.bfloat16), torch.no_grad():
        want = mapper(*inputs)
        got = cache.maps(mapper, *inputs)
    assert torch.equal(got, want) and got.dtype == want.dtype and cache.misses == 2
    again = cache.maps(mapper, *inputs)
    assert torch.equal(again, plain) and again.dtype == torch.float32 and cache.misses == 3


def test_the_cache_keeps_the_most_recent_maps_within_its_bytes(batch):
    mapper = _mapper()
    rgb, depth, K, poses = _inputs(batch)
    one = [x[:1] for x in (rgb, depth, K, poses)]
    size = FrozenMapCache(max_bytes=1 << 30).maps(mapper, *one).numel() * 4
    cache = FrozenMapCache(max_bytes=2 * size)
    cache.maps(mapper, rgb, depth, K, poses)                 # 3 maps into room for 2: example 0 evicted
    assert len(cache) == 2 and cache.misses == 3
    cache.maps(mapper, *(x[1:3] for x in (rgb, depth, K, poses)))
    assert cache.hits == 2
    cache.maps(mapper, *one)
    assert cache.misses == 4
    tiny = FrozenMapCache(max_bytes=size - 1)                # no map fits: computed every time, none kept
    tiny.maps(mapper, *one)
    tiny.maps(mapper, *one)
    assert len(tiny) == 0 and tiny.misses == 2
    with pytest.raises(ValueError, match="max_bytes"):
        FrozenMapCache(max_bytes=-1)


def _train_losses(task, batch, *, steps: int, lr: float) -> list[float]:
    """`steps` Adam steps of `task` on `batch` -> the losses."""
    opt = torch.optim.Adam([p for p in task.parameters() if p.requires_grad], lr=lr)
    losses = []
    for _ in range(steps):
        out = task(batch)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()
        losses.append(float(out["loss"].detach()))
    return losses


def test_frozen_detector_trains_through_the_cache_as_without_it(batch):
    """Frozen features, training: the maps come from the cache (one mapper pass per distinct example and
    time step) and the losses equal those of the task without it; fine-tuning and eval mode never use it."""
    losses = {}
    for mb in (0, 64):
        torch.manual_seed(0)
        task = build_task("detector", TINY, seed=0, frozen_map_cache_mb=mb)
        task.train()
        losses[mb] = _train_losses(task, batch, steps=4, lr=3e-3)
        if mb:
            assert task.frozen_maps.hits > 0 and task.frozen_maps.misses <= 6   # 3 records × 2 time steps
        else:
            assert task.frozen_maps is None
    torch.testing.assert_close(losses[64], losses[0], atol=1e-5, rtol=1e-5)
    tuned = build_task("detector", TINY, seed=0, freeze_features=False)
    assert tuned.frozen_maps is None
    task.eval()
    misses = task.frozen_maps.misses + task.frozen_maps.hits
    task.build_map(batch, 0)
    assert task.frozen_maps.misses + task.frozen_maps.hits == misses
    with pytest.raises(ValueError, match="frozen_map_cache_mb"):
        build_task("detector", TINY, seed=0, frozen_map_cache_mb=-1)


def test_a_cache_that_mostly_misses_turns_itself_off_and_one_that_hits_stays_on():
    """Once full (its first eviction), a cache whose next PROBE_LOOKUPS lookups hit less than MIN_HIT_RATE
    empties and disables itself (every example computed alone, and hashed, for nothing); its owner then
    computes batches directly. The misses of filling it do not count."""
    from core.tasks.frozen_maps import MIN_HIT_RATE, PROBE_LOOKUPS

    module = torch.nn.Linear(2, 2)
    double = lambda example: (example[0] * 2,)   # noqa: E731 — each example's "output", 1×3 float32: 12 bytes
    missing = FrozenMapCache(max_bytes=8 * 12)    # holds 8 outputs
    for i in range(100):                          # every example new: no hits
        examples = (4 * i + torch.arange(4.0))[:, None].expand(4, 3)   # 4 values never seen before
        torch.testing.assert_close(missing.outputs(module, double, [examples])[0], 2 * examples)
        if not missing.enabled:
            break
    # the 9th output filled it (evicting the 1st); the probe counted the next PROBE_LOOKUPS, judged after that call
    assert not missing.enabled and len(missing) == 0
    assert 9 + PROBE_LOOKUPS <= missing.misses < 9 + PROBE_LOOKUPS + 4
    with pytest.raises(RuntimeError, match="turned itself off"):
        missing.outputs(module, double, [torch.zeros(1, 3)])

    # Full, but hitting: 9 examples drawn at random against room for 8 (~8/9 of lookups hit once full)
    order = torch.randint(9, (4 * PROBE_LOOKUPS,), generator=torch.Generator().manual_seed(0))
    crowded = FrozenMapCache(max_bytes=8 * 12)
    for k in order.tolist():
        crowded.outputs(module, double, [torch.full((1, 3), float(k))])
    assert crowded.enabled and crowded._full and len(crowded) == 8
    assert crowded.hits >= MIN_HIT_RATE * (crowded.hits + crowded.misses)
    # Never full: never judged, whatever its hit rate
    roomy = FrozenMapCache(max_bytes=1 << 20)
    for i in range(2 * PROBE_LOOKUPS):
        roomy.outputs(module, double, [torch.full((1, 3), float(i))])
    assert roomy.enabled and roomy.hits == 0


def test_flow_over_frozen_features_trains_through_the_cache_as_without_it():
    """The flow task's inputs (both maps or volumes, and the occupied voxels) come from the cache in training:
    equal to the uncached ones (the slow reference: the batch computed directly), one computation per
    record, and the same losses over 3 Adam steps; eval mode never uses it."""
    from core.tasks.flow import FlowTask

    batch = records_to_batch([generate_record(TINY, seed=s, num_frames=2, moving_ego=True) for s in (3, 4)])
    for inputs in ("features", "volume"):
        losses = {}
        for mb in (0, 64):
            torch.manual_seed(0)
            task = FlowTask.from_preset(TINY, seed=0, inputs=inputs, frozen_input_cache_mb=mb)
            task.train()
            if mb:
                direct = task._pair_inputs([batch["rgb"][:, 0], batch["depth"][:, 0], batch["rgb"][:, 1],
                                            batch["depth"][:, 1], batch["pix_T_cam"], cam_T_ref(batch, 0, 0),
                                            cam_T_ref(batch, 1, 0)])
                for got, want in zip(task.flow_inputs(batch, 0), direct):
                    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
            losses[mb] = _train_losses(task, batch, steps=3, lr=1e-3)
            if mb:
                assert (task.frozen_inputs.misses, task.frozen_inputs.hits, len(task.frozen_inputs)) == (2, 6, 2)
                cached = task.flow_inputs(batch, 0)
                task.frozen_inputs.enabled = False   # as after a failed probe: the batch is computed directly
                for got, want in zip(task.flow_inputs(batch, 0), cached):
                    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
                assert task.frozen_inputs.hits == 8   # 6 + the cached call's 2; the direct call did not look up
                task.frozen_inputs.enabled = True
                task.eval()
                task.flow_inputs(batch, 0)
                assert task.frozen_inputs.hits + task.frozen_inputs.misses == 10   # eval: not looked up
            else:
                assert task.frozen_inputs is None
        torch.testing.assert_close(losses[64], losses[0], atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="frozen_input_cache_mb"):
        FlowTask.from_preset(TINY, frozen_input_cache_mb=-1)
