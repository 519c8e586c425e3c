"""Helpers of several ``cmax`` sub-commands that belong to none of them."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

__all__ = ["given", "named_pixels", "output_folder"]


def given(args: argparse.Namespace, names: dict[str, str]) -> dict[str, Any]:
    """``{keyword: value}`` of the options in ``names`` (option dest -> keyword) that were given (not None).

    >>> given(argparse.Namespace(seed=3, duration=None), {"seed": "seed", "duration": "duration_s"})
    {'seed': 3}
    """
    return {key: getattr(args, dest) for dest, key in names.items() if getattr(args, dest) is not None}


def output_folder(path: Path, contents: str) -> Path:
    """``-o``, refused before any work when it names a file (``contents``: what the folder will hold, for the
    message); the folder itself is made when the results are written.

    >>> output_folder(Path("results"), "the depth maps")
    PosixPath('results')
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"-o {path} is a file, not a folder: give a folder for {contents}")
    return path


def named_pixels(pixels, most: int = 5) -> str:
    """``"(x, y), (x, y), ..."``: the first ``most`` of ``pixels`` (K, 2), and ``, ...`` when there are more."""
    return ", ".join(f"({x}, {y})" for x, y in pixels[:most]) + (", ..." if len(pixels) > most else "")
