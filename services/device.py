"""Where the learner's networks train: `--device auto|cpu|cuda|cuda:N`.

`auto` takes the first GPU when torch sees one, else the CPU; an explicit `cuda` where there is
none (or `cuda:N` beyond the last) is refused in one line. Whatever the device, checkpoints hold
CPU-loadable tensors and load on either.
"""

from __future__ import annotations

import re

from tpdeb.services.config import ConfigError

DEVICE_RULE = re.compile(r"auto|cpu|cuda(:\d+)?")


def check_device_setting(value: str) -> str | None:
    """Why `value` is no device setting (None if it is one); needs no torch."""
    if DEVICE_RULE.fullmatch(value):
        return None
    return "must be auto, cpu, cuda or cuda:N (N the GPU's index)"


def resolve_device(value: str):
    """The torch.device for a device setting on this machine (ConfigError where it cannot be
    had)."""
    import torch

    problem = check_device_setting(value)
    if problem:
        raise ConfigError(f"device={value!r}: {problem}")
    available = torch.cuda.is_available()
    if value == "auto":
        return torch.device("cuda:0" if available else "cpu")
    if value == "cpu":
        return torch.device("cpu")
    if not available:
        raise ConfigError(f"device={value!r}: torch sees no CUDA device on this machine (a CPU "
                          "build of torch, no GPU or no driver); use --device cpu or auto")
    device = torch.device(value if ":" in value else "cuda:0")
    count = torch.cuda.device_count()
    if device.index >= count:
        raise ConfigError(f"device={value!r}: this machine has {count} CUDA device"
                          f"{'s' * (count != 1)} (cuda:0 to cuda:{count - 1})")
    return device


def describe(device) -> str:
    """The device as announced at start."""
    if device.type == "cuda":
        import torch

        return f"{device} ({torch.cuda.get_device_name(device)})"
    return "cpu"
