"""Where the network runs: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"``, checked against what torch sees.

Training (``train.device``) and prediction (``cmax depth --device``) name their device the same way.
"""
from __future__ import annotations

import re

import torch

__all__ = ["DEVICE_NAMES", "is_device_name", "resolve_device"]

#: What ``train.device`` and ``--device`` accept.
DEVICE_NAMES = "'cpu', 'cuda', 'cuda:N' or 'auto'"


def is_device_name(name: str) -> bool:
    """Whether ``name`` is one of :data:`DEVICE_NAMES` (spelling only; :func:`resolve_device` checks the device).

    Examples
    --------
    >>> [is_device_name(n) for n in ("cpu", "auto", "cuda", "cuda:1", "gpu")]
    [True, True, True, True, False]
    """
    return isinstance(name, str) and re.fullmatch(r"cpu|auto|cuda(:\d+)?", name) is not None


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """The device ``name`` stands for, for the process whose ``LOCAL_RANK`` is ``local_rank``: ``"cuda"`` is that
    rank's GPU (a ``torchrun`` job puts one rank on each), ``"auto"`` a GPU when torch sees one, else the CPU.

    Raises
    ------
    ValueError
        ``name`` is none of :data:`DEVICE_NAMES`, or a GPU was asked for where torch sees none (a CPU build of
        torch, or no device).
    """
    if not is_device_name(name):
        raise ValueError(f"device must be {DEVICE_NAMES}, got {name!r}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r}: torch {torch.__version__} sees no CUDA device; give cpu (or auto)")
        if name == "cuda":
            name = f"cuda:{local_rank}"
    return torch.device(name)
