"""An exponential moving average of a task's weights (Polyak averaging), the weights a run exports.

With a constant learning rate the weights after any one step carry that step's noise: the benchmark's
occupancy module's held-out loss swung ±10 % between checkpoints 200 steps apart, and a held-out
stopping rule then picks among noisy checkpoints. The average of the recent weights sits nearer the
middle of the basin the optimizer wanders in, and it changes slowly, so checkpoint-to-checkpoint
comparisons measure progress rather than noise. The optimizer never sees it: training is unchanged.

`WeightAverage(task, decay=d)` starts from the task's weights; `update(task, step)` after each
optimizer step moves every floating-point entry of the task's state_dict (parameters and BatchNorm
running statistics alike) towards the current value by `1 - d_t`, with the warm-up
`d_t = min(d, (1 + step) / (10 + step))` (as TensorFlow's ExponentialMovingAverage with num_updates)
so that the first steps' weights are not averaged with the random initialisation for hundreds of
steps. Integer entries (BatchNorm's step counters) are copied.
"""

from __future__ import annotations

import torch


def warmed_decay(decay: float, step: int) -> float:
    """The decay used after optimizer step `step` (1-based): `decay`, lowered while step is small."""
    return min(decay, (1.0 + step) / (10.0 + step))


class WeightAverage:
    """The moving average of one module's state_dict (module docstring)."""

    def __init__(self, module: torch.nn.Module, *, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"weight-average decay must lie in (0, 1), got {decay}")
        self.decay = decay
        self.state = {name: value.detach().clone() for name, value in module.state_dict().items()}

    @torch.no_grad()
    def update(self, module: torch.nn.Module, *, step: int) -> None:
        """Fold the module's current state into the average after optimizer step `step` (1-based)."""
        weight = 1.0 - warmed_decay(self.decay, step)
        averaged, current = [], []
        for name, value in module.state_dict().items():
            mine = self.state[name]
            if mine.is_floating_point():
                averaged.append(mine)
                current.append(value.detach())
            else:
                mine.copy_(value)
        if averaged:
            torch._foreach_lerp_(averaged, current, weight)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        missing, unexpected = sorted(set(self.state) - set(state)), sorted(set(state) - set(self.state))
        if missing or unexpected:
            raise KeyError(f"weight average does not fit the task (missing {missing[:3]}, unexpected "
                           f"{unexpected[:3]})")
        for name, value in state.items():
            self.state[name].copy_(value)
