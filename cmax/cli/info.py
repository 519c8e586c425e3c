"""The ``cmax info`` command: counts, duration, rate, resolution and polarity balance of event files."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from cmax.cli.recording import add_file_options, file_kwargs

__all__ = ["add_command", "run"]


def run(args: argparse.Namespace) -> int:
    """Print the summary lines of every file, in the order given; returns the exit status: 0, or 2 when a file could
    not be summarised.

    A file that cannot be read (missing, truncated, corrupt, refused for the options given) is one line
    ``cmax info: error: ...`` on stderr, and the files after it are still summarised (``cmax info *.raw`` over a
    folder holding one truncated recording); with ``--debug`` (or ``CMAX_DEBUG=1``) the first such error is raised,
    with its traceback."""
    from cmax._args import DEBUG_ENV, USER_ERRORS, one_line
    from cmax.io.info import file_info

    debug = bool(getattr(args, "debug", False)) or os.environ.get(DEBUG_ENV, "") not in ("", "0")
    failed = 0
    for path in args.files:
        try:
            lines = file_info(path, **file_kwargs(args, path)).lines()
        except USER_ERRORS as error:
            if debug:
                raise
            sys.stdout.flush()      # the blocks of the files before it come first, also in one log of both streams
            print(f"cmax info: error: {one_line(error)}", file=sys.stderr)
            failed += 1
            continue
        print("\n".join(lines))
    return 2 if failed else 0


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``info`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser("info", help="summary of event files",
                                   description="Counts, duration, rate, resolution, polarity balance and hot pixels "
                                   "of event files (any format cmax.io.read reads), one block per file.")
    parser.add_argument("files", nargs="+", type=Path, help="event files (any supported format)")
    add_file_options(parser)
    parser.set_defaults(run=run)
    return parser
