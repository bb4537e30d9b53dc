"""The torch devices a run may name, and whether this machine has the one it names."""

from __future__ import annotations

import re

__all__ = ["DEVICE", "check_device_available"]

DEVICE = re.compile(r"cpu|mps|cuda(:[0-9]{1,3})?")


def check_device_available(device: str) -> None:
    """A ValueError unless torch can use `device` on this machine (CUDA present, its index in
    range). Called for configs about to run, not for a run's config read back elsewhere."""
    if device == "cpu":
        return
    import torch

    if device == "mps":
        if not torch.backends.mps.is_available():
            raise ValueError("this machine has no Apple GPU torch can use (mps); use cpu")
        return
    if not torch.cuda.is_available():
        raise ValueError("CUDA is not available on this machine; use cpu")
    index = int(device.partition(":")[2] or 0)
    count = torch.cuda.device_count()
    if index >= count:
        raise ValueError(f"this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
