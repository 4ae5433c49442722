"""Choosing the torch device a command runs on."""

from __future__ import annotations

import torch

from headforge.errors import HeadforgeError


def resolve_device(name: str = "auto") -> torch.device:
    """``"auto"``: the current CUDA GPU when PyTorch sees one, else the CPU; ``"cpu"``,
    ``"cuda"``, ``"cuda:1"``: that device, after checking it exists (HeadforgeError otherwise)."""
    if name == "auto":
        return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise HeadforgeError(f"--device must be auto, cpu or cuda[:N], got {name!r}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise HeadforgeError(f"--device {name}: PyTorch sees no CUDA GPU here (torch {torch.__version__})")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise HeadforgeError(f"--device {name}: only {torch.cuda.device_count()} CUDA GPU(s) here")
    elif device.type != "cpu":
        raise HeadforgeError(f"--device must be auto, cpu or cuda[:N], got {name!r}")
    return device
