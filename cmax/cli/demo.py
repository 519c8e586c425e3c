"""The ``cmax demo`` command: the end-to-end demo (:func:`cmax.demo.run_demo`) on data it makes itself."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Callable

from cmax._args import add_duration_options, api_default, library_default, nonnegative_int, positive_float, sensor_size
from cmax.cli._common import given, output_folder

__all__ = ["add_command", "run", "settings_of"]

#: demo options (dest) -> DemoSettings fields; None on the command line = the library's default.
_DEMO_OPTIONS = {"seed": "seed", "duration": "duration_s", "window": "window_s"}


#: DemoSettings fields -> the options that set them, for the messages of refused settings.
_OPTION_OF = {"window_s": "--window-s", "duration_s": "--duration", "width": "--size width", "height": "--size height"}


def settings_of(args: argparse.Namespace):
    """The :class:`cmax.demo.DemoSettings` of the options given (the library's defaults for the others); a
    refused combination is a ValueError naming the options (``--window-s``), not the fields (``window_s``).

    >>> settings_of(argparse.Namespace(seed=None, duration=0.3, window=0.5, size=None))
    Traceback (most recent call last):
    ...
    ValueError: --window-s must be in (0, --duration=0.3], got 0.5
    """
    import re

    from cmax.demo import DemoSettings

    overrides = given(args, _DEMO_OPTIONS)
    if args.size is not None:
        overrides["width"], overrides["height"] = args.size
    try:
        return DemoSettings(**overrides)
    except ValueError as error:
        text = re.sub(r"\b(" + "|".join(_OPTION_OF) + r")\b", lambda m: _OPTION_OF[m.group(1)], str(error))
        raise ValueError(text) from None


def run(args: argparse.Namespace) -> int:
    """Run the demo, printing its progress lines (none with ``--quiet``) and where its report is; returns the exit
    status (0). A folder that already holds any
    of the demo's files (``<scene>.h5``, ``report.png``, ``report.md``, ``summary.txt``: an earlier demo's or a
    user's own) is refused before any work (exit 2, one line naming them) unless ``--overwrite``."""
    from cmax.demo import run_demo

    settings = settings_of(args)
    report = run_demo(output_folder(args.output, "the demo's h5 file and report"), settings=settings,
                      overwrite=args.overwrite, log=(lambda line: None) if args.quiet else print)
    print(f"demo report: {report.report_png}")
    return 0


def _demo_default(name: str) -> Callable[[], Any]:
    if name != "size":
        return library_default("cmax.demo:DemoSettings", name)
    width, height = (library_default("cmax.demo:DemoSettings", side) for side in ("width", "height"))
    return lambda: (width(), height())


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``demo`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser(
        "demo", help="end-to-end demo on data it makes itself",
        description="Render a synthetic scene, simulate its events, fit depth and motion with cmax.fit, run "
        "EMVS with the true poses, score both against ground truth, and write report.png, report.md and "
        "summary.txt.",
    )
    parser.add_argument("-o", "--output", type=Path, default=Path("demo_output"), help="output folder")
    api_default(parser.add_argument("--seed", type=nonnegative_int, default=None, help="seed of the scene"),
                _demo_default("seed"))
    api_default(parser.add_argument("--duration", type=positive_float, default=None,
                                    help="seconds of scene to simulate"), _demo_default("duration_s"))
    add_duration_options(parser, "window", dest="window", unit="s", help="length of the windows cmax.fit fits",
                         default=_demo_default("window_s"), aliases=("--window",))
    api_default(parser.add_argument("--size", type=sensor_size, default=None, metavar="WxH",
                                    help="sensor WIDTHxHEIGHT"), _demo_default("size"))
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the demo's files (indoor_flying.h5, report.png, report.md, summary.txt) when "
                             "-o holds them already, from an earlier demo or not (else refused)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines: only where the report is")
    parser.set_defaults(run=run)
    return parser
