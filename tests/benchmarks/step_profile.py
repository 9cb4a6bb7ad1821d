"""Pure helpers of the per-task train-step profile (tests/benchmarks/bench_train_step.py --tasks).

An *event* is anything with a `name` (or `key`, as torch.profiler's averaged events have) and a
`self_cpu_time_total` (microseconds of CPU time spent in the op itself, not in ops it called): the
`FunctionEvent`s of `torch.profiler.profile(...).events()` are such events. Because self times do not
overlap, their sum is the CPU time the profiler saw, and an op's share is its self time over that sum.

Which ops count as convolution (`is_conv_op`, case-insensitive): names containing "convolution"
(aten::convolution, aten::_convolution, aten::mkldnn_convolution, aten::convolution_backward,
aten::mkldnn_convolution_backward, aten::cudnn_convolution, the autograd nodes ConvolutionBackward0 and
MkldnnConvolutionBackward0 and their "autograd::engine::evaluate_function: ..." wrappers) or "conv"
followed by a digit, "_transpose", "_depthwise" or "_tbc" (aten::conv2d, aten::conv3d,
aten::conv_transpose3d, aten::slow_conv3d, aten::slow_conv3d_forward, aten::thnn_conv2d,
aten::_slow_conv2d_forward, aten::_slow_conv2d_backward, aten::slow_conv_transpose3d,
aten::_conv_depthwise2d). Names in which "conv" starts another word (aten::_convert_indices_from_coo_to_csr,
"convert_element_type") do not count. The wrappers (aten::conv3d -> aten::convolution -> ... ->
aten::mkldnn_convolution) nest, but self times do not double count: each holds only its own time.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable

_CONV = re.compile(r"convolution|conv(\d|_transpose|_depthwise|_tbc)", re.IGNORECASE)


def is_conv_op(name: str) -> bool:
    """Whether a profiler op name is a convolution (forward or backward); see the module docstring."""
    return _CONV.search(name) is not None


def _name(event) -> str:
    name = getattr(event, "name", None)
    return name if isinstance(name, str) else event.key


def self_time_by_op(events: Iterable) -> dict[str, float]:
    """Self CPU time (µs) summed per op name."""
    out: dict[str, float] = {}
    for e in events:
        name = _name(e)
        out[name] = out.get(name, 0.0) + float(e.self_cpu_time_total)
    return out


def conv_share(events: Iterable, predicate: Callable[[str], bool] = is_conv_op) -> float:
    """Share (0..1) of the events' total self CPU time spent in ops whose name satisfies `predicate`
    (0.0 when the events took no time)."""
    by_op = self_time_by_op(events)
    total = sum(by_op.values())
    if total <= 0:
        return 0.0
    return sum(t for name, t in by_op.items() if predicate(name)) / total


def top_ops(events: Iterable, n: int = 5, exclude: Callable[[str], bool] = is_conv_op) -> list[tuple[str, float]]:
    """The `n` ops (by name) with the most self CPU time among the ops `exclude` does not accept, each
    with its share of the total self CPU time of all events (conv ops included); largest first, ties
    by name."""
    by_op = self_time_by_op(events)
    total = sum(by_op.values())
    if total <= 0:
        return []
    kept = sorted(((name, t) for name, t in by_op.items() if not exclude(name)), key=lambda x: (-x[1], x[0]))
    return [(name, t / total) for name, t in kept[:n]]


def matched_ops(events: Iterable, predicate: Callable[[str], bool] = is_conv_op) -> list[str]:
    """Sorted names of the ops `predicate` accepts (what conv_share counted)."""
    return sorted(name for name in self_time_by_op(events) if predicate(name))
