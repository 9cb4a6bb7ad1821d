"""Hand-built training checkpoints for the bench tests: complete ones, as `services.training.checkpoints.
is_complete` reads them (a weights file that opens, a zip optimizer file, a readable state.json), and ones cut
short."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import save_file


def write_checkpoint(root: Path, step: int, *, torn: str | None = None) -> Path:
    """`root/checkpoint_<step>` with the three files; torn: "state" (no state.json, as a copy cut off before it)
    or "weights" (a truncated weights file beside a readable state.json) -> the checkpoint dir."""
    d = root / f"checkpoint_{step:08d}"
    d.mkdir(parents=True, exist_ok=True)
    save_file({"w": torch.full((4,), float(step))}, str(d / "task.safetensors"))
    torch.save({"step": step}, d / "optimizer.pt")
    if torn == "weights":
        data = (d / "task.safetensors").read_bytes()
        (d / "task.safetensors").write_bytes(data[:len(data) // 2])
    if torn != "state":
        (d / "state.json").write_text(json.dumps({"step": step, "config": {}, "metrics": {}}))
    return d
