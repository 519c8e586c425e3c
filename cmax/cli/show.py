"""The ``cmax show`` command: a time window of an event file drawn as a PNG (event frame, event-volume bins)."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from cmax._args import add_duration_options, api_default, library_default
from cmax.cli.recording import add_file_options, file_kwargs

__all__ = ["add_command", "run"]


def run(args: argparse.Namespace) -> int:
    """Draw the window and write the picture; returns the exit status (0). An existing picture at the output
    (a user's own ``FILE.png`` beside the recording) is refused before any work unless ``--overwrite``; a window
    without events (an empty file, a gap) is refused, as ``cmax fit`` refuses it, not drawn blank."""
    from cmax.show import render_window

    if args.bins is not None and args.mode == "frame":   # else taken and ignored: the frame has no bins
        raise ValueError(f"--bins applies to the event volume (--mode voxel or both), not --mode frame; got --bins "
                         f"{args.bins} with --mode frame")
    output = args.output or args.file.with_suffix(".png")
    if os.path.lexists(output) and not args.overwrite:
        raise FileExistsError(f"{output} exists: --overwrite replaces it, or give another -o")
    if output.parent.is_dir() and not os.access(output.parent, os.W_OK | os.X_OK):   # before the work, not after
        raise PermissionError(_unwritable(output, args.output is None))
    image = render_window(
        args.file, t0_s=args.t0, dt_s=args.dt, mode=args.mode, **({} if args.bins is None else {"bins": args.bins}),
        require_events=True,
        **file_kwargs(args)
    )
    from cmax.viz import save_image

    save_image(output, image)
    print(f"wrote {output}")
    return 0


def _unwritable(output: Path, beside: bool) -> str:
    """Why the picture ``output`` cannot be written (its folder refuses it), naming ``-o`` / ``--output``;
    ``beside``: ``output`` is the default, the recording's name with ``.png``."""
    where = ", beside the recording (the default)," if beside else ""
    return (f"cannot write the picture {output}{where} as its folder {output.parent} is not writable (a read-only data "
            "folder?); give -o/--output PATH.png in a folder you can write to")


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``show`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser(
        "show", help="draw a time window of an event file as a PNG",
        description="Draw the events of [t0, t0 + dt) as an event frame (ON blue, OFF red) "
        "or as the bins of the event volume; ground-truth depth is drawn beside them when the file has it.",
    )
    parser.add_argument("file", type=Path, help="event file (any supported format)")
    # t0, dt, bins: validated by cmax.show.render_window (one-line errors naming the value)
    parser.add_argument("--t0", type=float, default=0.0, help="window start in seconds after the first event")
    add_duration_options(parser, "window", dest="dt", unit="s", help="window length", default=lambda: 0.05,
                         aliases=("--dt",), kind=float)
    parser.set_defaults(dt=0.05)
    parser.add_argument("--mode", choices=("frame", "voxel", "both"), default="both",
                        help="event frame, event-volume bins, or both")
    api_default(parser.add_argument("--bins", type=int, default=None,
                                    help="bins of the event volume (--mode voxel or both)"),
                library_default("cmax.show:render_window", "bins"))
    parser.add_argument("-o", "--output", type=Path, default=None, help="picture path, .png, .jpg or .jpeg (default: FILE with .png, beside the recording)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing picture at the output")
    add_file_options(parser)
    parser.set_defaults(run=run)
    return parser
