"""core.device.resolve_device, the one `--device` resolver: a one-line ConfigError naming the accepted
values (not torch's backend list), and a clear one when CUDA is asked for where there is none."""

import pytest
import torch

from core.device import resolve_device
from core.errors import ConfigError


@pytest.mark.parametrize("choice", ["gpu", "meta", "cuda:x"])
def test_unknown_devices_name_the_accepted_values(choice):
    with pytest.raises(ConfigError) as info:
        resolve_device(choice)
    message = str(info.value)
    assert message == f"--device {choice!r}: expected cpu, cuda, cuda:N or auto" and "vulkan" not in message


def test_cpu_and_auto_resolve():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


def test_cuda_where_there_is_none():
    assert resolve_device("auto", cuda_available=False) == torch.device("cpu")
    for choice in ("cuda", "cuda:1"):
        with pytest.raises(ConfigError, match=f"--device {choice}: CUDA is not available on this machine"):
            resolve_device(choice, cuda_available=False)
    with pytest.raises(ConfigError, match="not available to this worker"):
        resolve_device("cuda", cuda_available=False, where="to this worker")
    assert resolve_device("cuda:1", cuda_available=True) == torch.device("cuda", 1)
