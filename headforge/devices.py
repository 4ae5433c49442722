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


def limit_threads(threads: int) -> None:
    """Cap this process's torch threads and the threads of numba's parallel kernels (the point
    splatter, the mesh rasteriser) at ``threads`` (numba: at most what it started with). For a
    process that shares a machine with others (a batch item, a ``torchrun`` rank): numba otherwise
    starts one thread per core in every process, and three 1-thread fits on 2 cores ran NHA's
    texture stage 10-30x slower (docs/batch_and_distributed.md)."""
    import numba

    threads = max(1, int(threads))
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
