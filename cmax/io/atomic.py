"""Atomic writes of small outputs: a temporary ``<name>.partial`` beside the target, then ``os.replace``.

An interrupted write leaves at most the ``.partial`` file, never a file under the final name
that looks complete. The big streaming writers (``H5Writer``, the EVT writers) follow the same rule
with their own temporary files.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["write_text_atomic", "save_npz_atomic"]


def _partial(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    path = Path(path)
    partial = _partial(path)
    partial.write_text(text, "utf-8")
    os.replace(partial, path)
    return path


def save_npz_atomic(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to ``path`` atomically (the name is kept as given); returns the path."""
    path = Path(path)
    partial = _partial(path)
    with open(partial, "wb") as file:  # a file object: numpy would append ".npz" to a path
        np.savez_compressed(file, **arrays)
    os.replace(partial, path)
    return path
