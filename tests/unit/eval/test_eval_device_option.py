"""`--device` of the eval commands: a one-line error naming the accepted values, not torch's backend list."""

import pytest
import torch

from services.cli.errors import CliError
from services.cli.eval import resolve_device


@pytest.mark.parametrize("choice", ["gpu", "meta", "cuda:x"])
def test_unknown_devices_name_the_accepted_values(choice):
    with pytest.raises(CliError) as info:
        resolve_device(choice)
    message = str(info.value)
    assert message == f"--device {choice!r}: expected cpu, cuda, cuda:N or auto" and "vulkan" not in message


def test_cpu_and_auto_resolve():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
