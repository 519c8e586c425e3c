"""The ``cmax depth`` command: depth and motion per window by the shipped depth-pose network.

The same command as ``python -m learned.predict``: its options and its run live in :mod:`learned.predict`.
"""
from __future__ import annotations

import argparse

__all__ = ["add_command"]


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``depth`` to an ``argparse`` sub-parser collection; returns the new parser."""
    from learned.predict import add_arguments, run

    parser = subparsers.add_parser(
        "depth", help="depth and motion per window by the learned depth-pose network",
        description="Depth maps [m] (npz and PNG with a colour bar) and twists of every window of an event file, "
        "by the depth-pose network shipped in the package (or --checkpoint); the same command as "
        "python -m learned.predict.")
    add_arguments(parser)
    parser.set_defaults(run=lambda args: run(args, "cmax depth"))
    return parser
