"""The ``cmax info`` command: counts, duration, rate, resolution and polarity balance of event files."""
from __future__ import annotations

import argparse
from pathlib import Path

from cmax.cli.recording import add_file_options, file_kwargs

__all__ = ["add_command", "run"]


def run(args: argparse.Namespace) -> int:
    """Print the summary lines of every file; returns the exit status (0)."""
    from cmax.io.info import file_info

    for path in args.files:
        print("\n".join(file_info(path, **file_kwargs(args, path)).lines()))
    return 0


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``info`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser("info", help="summary of event files",
                                   description="Counts, duration, rate, resolution, polarity balance and hot pixels "
                                   "of event files (any format cmax.io.read reads), one block per file.")
    parser.add_argument("files", nargs="+", type=Path, help="event files (any supported format)")
    add_file_options(parser)
    parser.set_defaults(run=run)
    return parser
