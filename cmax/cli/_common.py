"""Helpers of several ``cmax`` sub-commands that belong to none of them."""
from __future__ import annotations

import argparse
from typing import Any

__all__ = ["given"]


def given(args: argparse.Namespace, names: dict[str, str]) -> dict[str, Any]:
    """``{keyword: value}`` of the options in ``names`` (option dest -> keyword) that were given (not None).

    >>> given(argparse.Namespace(seed=3, duration=None), {"seed": "seed", "duration": "duration_s"})
    {'seed': 3}
    """
    return {key: getattr(args, dest) for dest, key in names.items() if getattr(args, dest) is not None}
