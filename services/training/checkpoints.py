"""Training checkpoints: one directory per saved step, loadable without unpickling code.

Layout of a checkpoint directory:

    task.safetensors   the task's state_dict (every parameter and buffer)
    average.safetensors  the moving average of that state_dict (runs with --ema-decay > 0 only)
    optimizer.pt       the optimizer's state_dict, read back with torch.load(weights_only=True)
    state.json         {"step": int, "config": TrainJobConfig.to_dict(), "metrics": {...}}

Ray Train stores these directories under RUN_DIR/ray_train/ (it picks the latest one for a rerun or
a retry); the in-process loop (workers=0) keeps them under RUN_DIR/checkpoints/ itself, with the same
"latest wins, keep the newest K" rule (`LocalCheckpointStore`).
"""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from core.errors import N3dmapError
from services.durable import fsync_path, fsync_tree
from services.training.weight_average import WeightAverage

TASK_FILE = "task.safetensors"
AVERAGE_FILE = "average.safetensors"
OPTIMIZER_FILE = "optimizer.pt"
STATE_FILE = "state.json"
CHECKPOINT_PREFIX = "checkpoint_"
RETIRED_PREFIX = ".retired-"   # a checkpoint dir renamed out of the checkpoint names, to be deleted (commit)
# Identity fields (TrainJobConfig.identity) that checkpoints written before the field existed lack: the
# value those runs had.
IDENTITY_DEFAULTS = {"ema_decay": 0.0}


class CheckpointError(N3dmapError):
    """A checkpoint is missing, corrupt, or belongs to a different run."""


@dataclass(frozen=True)
class CheckpointState:
    """What `load_checkpoint` restores besides the tensors."""

    step: int
    config: dict
    metrics: dict
    # (epoch, batches of that epoch already trained): where the data stream stood, written only by a run
    # stopped by a signal (loop.py), so that its resume reads exactly the batches the run would have read
    data_position: tuple[int, int] | None = None


def checkpoint_dir_name(step: int) -> str:
    return f"{CHECKPOINT_PREFIX}{step:08d}"


def save_checkpoint(directory: str | Path, *, task: torch.nn.Module, optimizer: torch.optim.Optimizer,
                    step: int, config: dict, metrics: dict, average: WeightAverage | None = None,
                    data_position: tuple[int, int] | None = None) -> Path:
    """Write the task, optimizer, step and config (and the weight average, if any; the data position, if
    given: CheckpointState) into `directory` (created if missing)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    save_file(_cpu_tensors(task.state_dict()), str(directory / TASK_FILE))
    if average is not None:
        save_file(_cpu_tensors(average.state_dict()), str(directory / AVERAGE_FILE))
    torch.save(optimizer.state_dict(), directory / OPTIMIZER_FILE)
    state = {"step": int(step), "config": config, "metrics": _json_safe(metrics)}
    if data_position is not None:
        state["data_position"] = [int(v) for v in data_position]
    (directory / STATE_FILE).write_text(json.dumps(state, indent=1, sort_keys=True))
    return directory


def read_checkpoint_state(directory: str | Path) -> CheckpointState:
    """Read only state.json (step, config, metrics) of a checkpoint."""
    path = Path(directory) / STATE_FILE
    try:
        state = json.loads(path.read_text())
        position = state.get("data_position")
        return CheckpointState(step=int(state["step"]), config=dict(state["config"]),
                               metrics=dict(state.get("metrics", {})),
                               data_position=None if position is None else (int(position[0]), int(position[1])))
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {directory}: missing {STATE_FILE}") from None
    except (ValueError, KeyError, TypeError) as e:
        raise CheckpointError(f"checkpoint {directory}: corrupt {STATE_FILE} ({e})") from None


def load_checkpoint(directory: str | Path, *, task: torch.nn.Module,
                    optimizer: torch.optim.Optimizer | None = None, average: WeightAverage | None = None,
                    averaged_weights: bool = False) -> CheckpointState:
    """Load a checkpoint into `task` (and `optimizer`, `average` if given); tensors go to the task's device.

    averaged_weights: load the checkpoint's weight average into `task` instead of its last step's
    weights, where it has one (the weights a run exports); a checkpoint without one loads as usual.
    """
    directory = Path(directory)
    state = read_checkpoint_state(directory)
    use_average = averaged_weights and (directory / AVERAGE_FILE).is_file()
    tensors = _read_tensors(directory, AVERAGE_FILE if use_average else TASK_FILE)
    try:
        task.load_state_dict(tensors, strict=True)
    except RuntimeError as e:
        first_line = str(e).strip().splitlines()[0]
        raise CheckpointError(f"checkpoint {directory} does not fit this task: {first_line}") from None
    if average is not None:
        if not (directory / AVERAGE_FILE).is_file():
            raise CheckpointError(f"checkpoint {directory}: missing {AVERAGE_FILE} (the run keeps a weight "
                                  "average, the checkpoint has none)")
        try:
            average.load_state_dict(_read_tensors(directory, AVERAGE_FILE))
        except KeyError as e:
            raise CheckpointError(f"checkpoint {directory}: {AVERAGE_FILE}: {e.args[0]}") from None
    if optimizer is not None:
        device = _module_device(task)
        try:
            opt_state = torch.load(directory / OPTIMIZER_FILE, map_location=device, weights_only=True)
        except FileNotFoundError:
            raise CheckpointError(f"checkpoint {directory}: missing {OPTIMIZER_FILE}") from None
        optimizer.load_state_dict(opt_state)
    return state


def check_same_run(saved_config: dict, identity: dict, where: str | Path) -> None:
    """Refuse to resume a checkpoint written by a different task / objective / preset."""
    saved = {k: saved_config.get(k, IDENTITY_DEFAULTS.get(k)) for k in identity}
    if saved != identity:
        diffs = ", ".join(f"{k}: checkpoint {saved[k]!r} vs now {identity[k]!r}"
                          for k in identity if saved[k] != identity[k])
        raise CheckpointError(f"run dir holds a different run ({diffs}) in {where}; "
                              f"use a new --run-dir or the original options")


class LocalCheckpointStore:
    """Checkpoints of the in-process loop: `root/checkpoint_<step>`; newest wins; keeps `keep`."""

    def __init__(self, root: str | Path, *, keep: int) -> None:
        self.root = Path(root)
        self.keep = keep

    def list(self) -> list[Path]:
        """Complete checkpoints, oldest first (a dir counts once its state.json exists)."""
        if not self.root.is_dir():
            return []
        found = [p for p in self.root.iterdir()
                 if p.is_dir() and p.name.startswith(CHECKPOINT_PREFIX) and (p / STATE_FILE).is_file()]
        return sorted(found, key=lambda p: p.name)

    def latest(self) -> Path | None:
        found = self.list()
        return found[-1] if found else None

    def commit(self, staged: Path, step: int) -> Path:
        """Move a fully written checkpoint dir into place (atomic rename), then prune old ones.

        A dir is deleted only after it is renamed out of the checkpoint names (RETIRED_PREFIX): deleted in place, a
        deletion cut short (a second Ctrl-C, which stops at once; an error) left a checkpoint dir with its
        state.json and without its weights, which `list` counted and resume then failed on."""
        self.root.mkdir(parents=True, exist_ok=True)
        for leftover in self.root.glob(f"{RETIRED_PREFIX}*"):   # a deletion an earlier commit did not finish
            shutil.rmtree(leftover, ignore_errors=True)
        final = self.root / checkpoint_dir_name(step)
        replaced = self._retire(final) if final.exists() else None
        # On disk before the rename makes it the newest, and the rename on disk before older ones are deleted:
        # after a power loss the newest name holds whole files, or the older checkpoints are still there.
        fsync_tree(staged)
        os.replace(staged, final)
        fsync_path(self.root)
        retired = [self._retire(old) for old in self.list()[:-self.keep]]
        for path in [replaced, *retired]:
            if path is not None:
                shutil.rmtree(path, ignore_errors=True)
        return final

    def _retire(self, checkpoint: Path) -> Path:
        """Rename `checkpoint` out of the checkpoint names (one atomic step), to be deleted."""
        retired = self.root / f"{RETIRED_PREFIX}{checkpoint.name}"
        if retired.exists():
            shutil.rmtree(retired)
        os.replace(checkpoint, retired)
        return retired


def newest_complete_checkpoint(root: str | Path) -> Path | None:
    """The newest checkpoint under `root` (by name) that `is_complete`, or None."""
    for candidate in reversed(LocalCheckpointStore(root, keep=1).list()):
        if is_complete(candidate):
            return candidate
    return None


def is_complete(checkpoint: Path) -> bool:
    """Whether a checkpoint dir has its three files, a readable state.json and a weights file that opens (and,
    for a run that keeps a weight average, an average file that opens): a copy cut short (Ray copies each
    checkpoint into its storage; a dying worker or node stops it part way) is not. Why the average too: a torn
    one passed, and every resume then failed loading it instead of falling back to the checkpoint before."""
    from safetensors import safe_open

    if not all((checkpoint / name).is_file() for name in (TASK_FILE, OPTIMIZER_FILE, STATE_FILE)):
        return False
    if not zipfile.is_zipfile(checkpoint / OPTIMIZER_FILE):   # torch.save's zip: a copy cut short has no directory
        return False
    try:
        state = read_checkpoint_state(checkpoint)
        weights = [TASK_FILE] + ([AVERAGE_FILE] if float(state.config.get("ema_decay") or 0.0) > 0 else [])
        for name in weights:
            with safe_open(str(checkpoint / name), framework="pt"):
                pass
    except Exception:  # CheckpointError, a missing average, or safetensors' own types for truncated files
        return False
    return True


def _cpu_tensors(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    # clone(): safetensors refuses tensors that share storage; contiguous CPU copies are always safe.
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in state.items()}


def _read_tensors(directory: Path, name: str) -> dict[str, torch.Tensor]:
    try:
        return load_file(str(directory / name))
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {directory}: missing {name}") from None
    except Exception as e:  # safetensors raises its own error types for truncated/corrupt files
        raise CheckpointError(f"checkpoint {directory}: cannot read {name} ({e})") from None


def _module_device(module: torch.nn.Module) -> torch.device:
    for p in module.parameters():
        return p.device
    return torch.device("cpu")


def _json_safe(metrics: dict) -> dict:
    out = {}
    for k, v in metrics.items():
        if isinstance(v, torch.Tensor):
            v = v.item()
        out[k] = float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v
    return out
