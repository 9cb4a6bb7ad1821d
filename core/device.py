"""The torch device of a `--device` choice: the one resolver the CLI, training, inference and the
benchmark share, so that "auto" and a missing GPU mean the same everywhere."""

from __future__ import annotations

import torch

from core.errors import ConfigError

CHOICES = "cpu, cuda, cuda:N or auto"


def resolve_device(choice: str, *, cuda_available: bool | None = None, where: str = "on this machine") -> torch.device:
    """'auto' -> cuda if available else cpu; 'cpu', 'cuda' and 'cuda:N' as given.

    cuda_available: whether this process may use CUDA (default: torch.cuda.is_available(); a Ray
    worker without a GPU share passes False). `where` names that scope in the error. Raises
    ConfigError naming the accepted values for anything else, and when CUDA is asked for but unavailable.
    """
    if cuda_available is None:
        cuda_available = torch.cuda.is_available()
    if choice == "auto":
        return torch.device("cuda" if cuda_available else "cpu")
    try:
        device = torch.device(choice)
    except RuntimeError:  # torch's message lists every backend it knows; name the ones n3dmap runs on
        raise ConfigError(f"--device {choice!r}: expected {CHOICES}") from None
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"--device {choice!r}: expected {CHOICES}")
    if device.type == "cuda" and not cuda_available:
        raise ConfigError(f"--device {choice}: CUDA is not available {where}")
    return device
