"""A tiny real task for harness tests: linear regression on record statistics (no core models)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from services.training.loop import TaskSpec

TRUE_W = np.array([1.5, -2.0, 0.5], dtype=np.float32)


def toy_records(n: int, seed: int = 0) -> list[dict]:
    """Records {"x": float32 3, "y": float32 ()} with y = TRUE_W · x."""
    rng = np.random.default_rng(seed)
    xs = rng.normal(size=(n, 3)).astype(np.float32)
    return [{"x": x, "y": np.float32(x @ TRUE_W)} for x in xs]


class ToyTask(nn.Module):
    """forward(batch) -> {"loss": MSE, "abs_err": mean |error|}; loss is NaN from call `nan_at_call`."""

    def __init__(self, *, nan_at_call: int | None = None, draws: list[float] | None = None) -> None:
        super().__init__()
        self.head = nn.Linear(3, 1)
        self.nan_at_call = nan_at_call
        self.draws = draws   # when given: one draw of torch's global generator per call, as real tasks draw
        self.calls = 0
        self.pred_dtypes: list[torch.dtype] = []   # the linear layer's output dtype, per call (autocast: bf16)

    def exported_modules(self) -> dict:
        return {"head": self.head}

    def forward(self, batch: dict) -> dict:
        self.calls += 1
        if self.draws is not None:
            self.draws.append(float(torch.rand(())))
        pred = self.head(batch["x"]).squeeze(-1)                 # B
        self.pred_dtypes.append(pred.dtype)
        err = pred - batch["y"]                                   # B
        loss = (err ** 2).mean()
        if self.nan_at_call is not None and self.calls >= self.nan_at_call:
            loss = loss * float("nan")
        return {"loss": loss, "abs_err": err.abs().mean()}


def _to_batch(records: list[dict], device) -> dict:
    return {"x": torch.from_numpy(np.stack([r["x"] for r in records])).to(device),   # B×3
            "y": torch.from_numpy(np.stack([r["y"] for r in records])).to(device)}   # B


def toy_spec(nan_at_call: int | None = None, draws: list[float] | None = None) -> TaskSpec:
    return TaskSpec(build=lambda config, device: ToyTask(nan_at_call=nan_at_call, draws=draws).to(device),
                    to_batch=_to_batch, exported=lambda task: task.exported_modules())
