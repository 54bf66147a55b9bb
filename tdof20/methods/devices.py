"""Where a method runs: the device, the processes of a launch (torchrun), mixed precision.

    dev = select_device("auto")              # the first CUDA GPU, else Apple MPS, else the CPU
    rank, local_rank, world = distributed()  # (0, 0, 1) without a launcher
    batch = to_device(batch, dev)
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import torch

from tdof20.errors import TdofError


def select_device(device: str = "auto") -> torch.device:
    """'auto' -> the first CUDA GPU, else Apple MPS, else the CPU; anything else as torch reads it."""
    if device in (None, "", "auto"):
        if torch.cuda.is_available():
            return torch.device("cuda")
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except RuntimeError as e:
        raise TdofError(f"--device: {e}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise TdofError(f"--device {device}: this torch has no CUDA device")
    return dev


def distributed() -> tuple[int, int, int]:
    """(rank, local_rank, world_size) from the launcher's environment (1 process without one)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 0, 1
    return int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0")), world


def is_main_process() -> bool:
    """True in a single process and in process 0 of a launch (torchrun): the one that writes and prints."""
    return distributed()[0] == 0


def amp_dtype(dev: torch.device) -> torch.dtype:
    return torch.bfloat16 if dev.type == "cuda" and torch.cuda.is_bf16_supported() else torch.float16


def to_device(batch: Mapping, dev: torch.device) -> dict:
    """The tensors of a batch on ``dev`` (others as they are)."""
    pin = dev.type == "cuda"
    return {k: v.to(dev, non_blocking=pin) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
