"""The ``cmax`` command line: one entry point, one sub-command per task.

``cmax info FILE``            counts, duration, rate, resolution, polarity balance
``cmax show FILE -o out.png`` event frame or event-volume bins of a time window
``cmax scene PRESET -o F.h5``  synthetic scene: events plus ground-truth depth and poses
``cmax fit FILE --K ...``     depth and motion per window by contrast maximization
``cmax depth FILE -o out/``   depth and motion per window by the shipped depth-pose network
``cmax emvs FILE --poses ...`` semi-dense depth from known poses (EMVS)
``cmax demo``                 the end-to-end demo on data it makes itself
``cmax simulate IN -o OUT``   videos to event files (ESIM), with a resumable manifest
``cmax manifest merge ...``   join the manifests of several machines or shards

One module per sub-command (:mod:`~cmax.cli.info`, :mod:`~cmax.cli.show`, :mod:`~cmax.cli.scene`,
:mod:`~cmax.cli.fit`, :mod:`~cmax.cli.depth`, :mod:`~cmax.cli.emvs`, :mod:`~cmax.cli.demo`,
:mod:`~cmax.cli.simulate`, :mod:`~cmax.cli.manifest`), each with ``add_command(subparsers)`` and
``run(args) -> exit status``; :mod:`~cmax.cli.recording` holds the options and helpers shared by the
commands that read a recording (``--size``, ``--time-unit``, ``--t0``/``--t1``, ``--K``, ``--calib``).
Each sub-command parses its arguments, calls the library, and prints or writes the result; no
numerical code lives here. Building the parser loads neither torch nor OpenCV.
"""
from __future__ import annotations

import argparse
import importlib
from typing import Sequence

from cmax._args import ArgumentParser, run_main

__all__ = ["COMMANDS", "main", "build_parser"]

#: The sub-command modules of :mod:`cmax.cli`, in the order ``cmax --help`` lists them.
COMMANDS: tuple[str, ...] = ("info", "show", "scene", "fit", "depth", "emvs", "demo", "simulate", "manifest")


def build_parser() -> argparse.ArgumentParser:
    """The ``cmax`` argument parser with all sub-commands (each registered by its module's ``add_command``).

    >>> parser = build_parser()
    >>> parser.parse_args(["info", "a.h5", "--size", "346x260"]).size
    (346, 260)
    """
    from cmax import __version__

    parser = ArgumentParser(
        prog="cmax", description="Event cameras: simulation, file formats, contrast maximization."
    )
    parser.add_argument("--version", action="version", version=f"evtslowtv {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"{__name__}.{name}").add_command(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cmax`` console script; returns the exit status.

    A bad argument, and an error a user can fix (a bad or missing file, a value
    out of range: ``ValueError`` including :class:`cmax.io.FormatError`,
    ``TypeError``, ``OSError``), prints ONE line ``cmax COMMAND: error: ...`` on
    stderr and exits with status 2 instead of a traceback; ``cmax --debug ...``
    or ``CMAX_DEBUG=1`` shows the traceback.
    """
    return run_main(build_parser(), None, argv, prog=lambda args: f"cmax {args.command}")
