"""The per-task step profile's pure helpers (tests/benchmarks/step_profile.py) against slow, obvious
references on hand-built fake profiler events, plus one real torch.profiler trace of a tiny Conv3d."""

from __future__ import annotations

import random
from types import SimpleNamespace

import pytest

from tests.benchmarks.step_profile import conv_share, is_conv_op, matched_ops, self_time_by_op, top_ops

# Op names seen in real CPU traces of the tasks' steps (torch 2.13), classified by hand.
CONV_NAMES = [
    "aten::conv2d", "aten::conv3d", "aten::conv_transpose3d", "aten::convolution", "aten::_convolution",
    "aten::mkldnn_convolution", "aten::convolution_backward", "aten::mkldnn_convolution_backward",
    "aten::slow_conv3d", "aten::slow_conv3d_forward", "aten::thnn_conv2d", "aten::_slow_conv2d_forward",
    "aten::_slow_conv2d_backward", "aten::slow_conv_transpose3d", "aten::_conv_depthwise2d",
    "ConvolutionBackward0", "MkldnnConvolutionBackward0",
    "autograd::engine::evaluate_function: ConvolutionBackward0",
]
OTHER_NAMES = [
    "aten::add", "aten::mul", "aten::copy_", "aten::where", "aten::grid_sampler_3d", "aten::addmm",
    "aten::_convert_indices_from_coo_to_csr", "aten::convert_element_type", "aten::native_batch_norm",
    "Optimizer.step#Adam.step", "autograd::engine::evaluate_function: AddBackward0", "aten::conversion",
]


def _events(rng: random.Random, n: int, *, attr: str = "name") -> list:
    names = CONV_NAMES + OTHER_NAMES
    return [SimpleNamespace(**{attr: rng.choice(names), "self_cpu_time_total": rng.choice([0.0, 1.0, 2.5, 7.0, 40.0])})
            for _ in range(n)]


def _ref_conv_share(events) -> float:
    total = conv = 0.0
    for e in events:
        name = getattr(e, "name", None) or e.key
        total += e.self_cpu_time_total
        if name in CONV_NAMES:
            conv += e.self_cpu_time_total
    return conv / total if total else 0.0


def _ref_top_non_conv(events, n):
    names = []
    for e in events:
        name = getattr(e, "name", None) or e.key
        if name not in names:
            names.append(name)
    total = sum(e.self_cpu_time_total for e in events)
    per = {}
    for name in names:
        t = 0.0
        for e in events:
            if (getattr(e, "name", None) or e.key) == name:
                t += e.self_cpu_time_total
        per[name] = t
    ranked = [x for x in names if x not in CONV_NAMES]
    # selection sort: most time first, ties by name
    out = []
    while ranked and len(out) < n:
        best = ranked[0]
        for x in ranked[1:]:
            if per[x] > per[best] or (per[x] == per[best] and x < best):
                best = x
        ranked.remove(best)
        out.append((best, per[best] / total))
    return out


@pytest.mark.parametrize("name", CONV_NAMES)
def test_conv_names_count(name):
    assert is_conv_op(name)


@pytest.mark.parametrize("name", OTHER_NAMES)
def test_other_names_do_not(name):
    assert not is_conv_op(name)


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("attr", ["name", "key"])
def test_conv_share_and_top_ops_match_slow_reference(seed, attr):
    rng = random.Random(seed)
    events = _events(rng, rng.randint(1, 60), attr=attr)
    assert conv_share(events) == pytest.approx(_ref_conv_share(events), abs=1e-12)
    got = top_ops(events, 5)
    want = _ref_top_non_conv(events, 5) if sum(e.self_cpu_time_total for e in events) else []
    assert [g[0] for g in got] == [w[0] for w in want]
    assert [g[1] for g in got] == pytest.approx([w[1] for w in want])
    assert matched_ops(events) == sorted({getattr(e, attr) for e in events} & set(CONV_NAMES))


def test_hand_counted_example():
    ev = [SimpleNamespace(name=n, self_cpu_time_total=t) for n, t in [
        ("aten::conv3d", 1.0), ("aten::mkldnn_convolution", 30.0), ("aten::add", 20.0),
        ("aten::convolution_backward", 40.0), ("aten::add", 5.0), ("aten::copy_", 4.0)]]
    assert self_time_by_op(ev)["aten::add"] == 25.0
    assert conv_share(ev) == pytest.approx(71.0 / 100.0)
    assert top_ops(ev, 1) == [("aten::add", pytest.approx(0.25))]
    assert conv_share(ev, predicate=lambda n: n == "aten::copy_") == pytest.approx(0.04)
    assert conv_share([]) == 0.0 and top_ops([], 5) == []


def test_real_profiler_events_of_a_conv3d_step(one_torch_thread):
    import torch

    conv = torch.nn.Conv3d(2, 4, 3, padding=1)
    x = torch.randn(1, 2, 6, 6, 6)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        conv(x).square().sum().backward()
    events = list(prof.events())
    names = matched_ops(events)
    assert "aten::conv3d" in names and "aten::convolution_backward" in names
    share = conv_share(events)
    assert 0.0 < share < 1.0
    assert all(not is_conv_op(n) for n, _ in top_ops(events, 5))
