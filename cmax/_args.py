"""Command-line plumbing shared by ``cmax`` and ``python -m learned.*``: argument types, help, one-line errors.

* ``type=`` validators (:func:`finite_float`, :func:`positive_float`, :func:`positive_int`, ...)
  refuse ``nan``, ``inf`` and out-of-range values while arguments are parsed, with
  a message naming the argument;
* :class:`ArgumentParser` prints a bad argument as ONE line,
  ``PROG: error: MESSAGE (see PROG --help)``, and exits with status 2;
* :class:`HelpFormatter` appends every option's default to its help text, taking
  it from the library (:func:`api_default`) where the library owns it, so that the
  command line and the API share one source of defaults;
* :func:`run_main` runs a command and turns the user errors of the public
  boundaries (:data:`USER_ERRORS`: ``ValueError`` -- including
  :class:`cmax.io.FormatError` and :class:`learned.checkpoint.CheckpointError` --,
  ``TypeError``, ``OSError`` and ``MemoryError``) into ``PROG: error: MESSAGE`` on
  one line and exit status 2, without a traceback. ``--debug`` or the
  environment variable ``CMAX_DEBUG=1`` shows the traceback instead.

No import here loads torch or OpenCV (the parsers are built at start-up).
"""
from __future__ import annotations

import argparse
import math
import os
import re
import sys
import warnings
from typing import Any, Callable, Sequence

from cmax._signals import Terminated, ignore_while_exiting, sigterm_as_interrupt, terminated_by

__all__ = [
    "ArgumentParser", "HelpFormatter", "USER_ERRORS", "DEBUG_ENV", "api_default", "run_main", "one_line",
    "finite_float", "positive_float", "nonnegative_float", "positive_int", "nonnegative_int", "sensor_size",
    "float_list", "add_duration_options",
]

#: Exceptions that mean "the user gave something wrong" at the library's public boundaries.
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, TypeError, OSError, MemoryError)
#: Environment variable that makes :func:`run_main` show tracebacks (like ``--debug``).
DEBUG_ENV = "CMAX_DEBUG"


# -- argument types ---------------------------------------------------------------------
def _number(text: str, kind: type, what: str, *, above: float | None = None,
            at_least: float | None = None) -> float | int:
    """``kind(text)``, finite, ``> above`` / ``>= at_least``; else ArgumentTypeError ``expected WHAT, got TEXT``."""
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r} (not finite)")
    if (above is not None and value <= above) or (at_least is not None and value < at_least):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite number (``nan``, ``inf`` refused)."""
    return float(_number(text, float, "a finite number"))


def positive_float(text: str) -> float:
    """A finite number > 0."""
    return float(_number(text, float, "a finite number > 0", above=0))


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    return float(_number(text, float, "a finite number >= 0", at_least=0))


def int_at_least(minimum: int):
    """An ``argparse`` type: a whole number >= ``minimum``.

    >>> int_at_least(2)("5")
    5
    """
    def parse(text: str) -> int:
        return int(_number(text, int, f"a whole number >= {minimum}", at_least=minimum))

    parse.__doc__ = f"A whole number >= {minimum}."
    return parse


#: A whole number >= 1.
positive_int = int_at_least(1)
#: A whole number >= 0.
nonnegative_int = int_at_least(0)


def sensor_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` (or ``WIDTH,HEIGHT``) in pixels, each in [1, 65535], at most
    :data:`cmax.events.MAX_SENSOR_PIXELS` in all (the rules of :class:`cmax.Events`)."""
    from cmax.events import _check_sensor_size

    try:
        width, height = (int(part) for part in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 346x260, got {text!r}") from None
    try:
        return _check_sensor_size(width, height)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{error} (got {text!r})") from None


def grid_shape(text: str) -> tuple[int, int]:
    """``ROWS,COLS`` (or ``ROWSxCOLS``) of a grid, each a positive integer."""
    try:
        rows, cols = (int(part) for part in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ROWS,COLS such as 24,32, got {text!r}") from None
    if rows < 1 or cols < 1:
        raise argparse.ArgumentTypeError(f"rows and columns must be positive, got {text!r}")
    return rows, cols


def float_list(counts: tuple[int, ...], what: str) -> Callable[[str], tuple[float, ...]]:
    """A type of ``counts`` comma-separated finite numbers (``what`` names them in the message)."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be comma-separated numbers, got {text!r}") from None
        if len(values) not in counts or not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(
                f"{what} must be {' or '.join(map(str, counts))} finite numbers, got {text!r}")
        return values

    parse.__name__ = what
    return parse


# -- lengths of time with their unit in the option's name -------------------------------------
#: Units of :func:`add_duration_options`, in milliseconds (whole numbers: conversions multiply or divide by them).
_UNIT_MS = {"ms": 1, "s": 1000}


class _InUnit(argparse.Action):
    """Stores its value converted into the unit of its ``dest``: ``value * multiply / divide`` to 15 significant
    digits, so that ``--window-s 0.0333`` stores what ``--window-ms 33.3`` does (not 33.300000000000004): one
    window, one record for ``--resume`` to compare, whichever spelling gave it."""

    def __init__(self, *args: Any, multiply: int = 1, divide: int = 1, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.multiply, self.divide = multiply, divide

    def __call__(self, parser, namespace, values, option_string=None):  # noqa: D102 (argparse API)
        setattr(namespace, self.dest, float(f"{values * self.multiply / self.divide:.15g}"))


def add_duration_options(parser: argparse.ArgumentParser, name: str, *, dest: str, unit: str, help: str,
                         default: Callable[[], float] | str | None = None, aliases: Sequence[str] = (),
                         kind: Callable[[str], float] | None = None) -> tuple[argparse.Action, argparse.Action]:
    """Add ``--NAME-ms`` [ms] and ``--NAME-s`` [s], one length of time in either unit (mutually exclusive), stored
    in ``args.DEST`` in ``unit`` whichever is given: every command names a window the same two ways, so that
    neither spelling learned on one command is refused (or, abbreviated, misread) on another.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The (sub-)command's parser.
    name : str
        The option's stem: ``"window"`` adds ``--window-ms`` and ``--window-s``.
    dest : str
        The attribute of the parsed arguments that holds the length (None when neither option is given).
    unit : {'ms', 's'}
        The unit of ``args.DEST``: the value of the option in the other unit is converted (times or over 1000).
    help : str
        What the length is, without its unit (the help appends ``[ms]`` / ``[s]`` and the default).
    default : callable or str, optional
        The default: a callable giving it in ``unit`` (the library's, shown in ``--help`` in each option's unit), or
        a sentence saying what it is (``"the checkpoint config's data.window_us"``).
    aliases : sequence of str
        Earlier spellings of the option in seconds, kept working as the same option (``("--window",)``).
    kind : callable, optional
        The ``argparse`` type of the value (default :func:`positive_float`).

    Returns
    -------
    (argparse.Action, argparse.Action)
        The actions of ``--NAME-ms`` and ``--NAME-s``.

    >>> parser = ArgumentParser(prog="p")
    >>> _ = add_duration_options(parser, "window", dest="window_ms", unit="ms", help="window length")
    >>> parser.parse_args(["--window-s", "0.15"]).window_ms, parser.parse_args(["--window-ms", "150"]).window_ms
    (150.0, 150.0)
    """
    if unit not in _UNIT_MS:
        raise ValueError(f"unit must be one of {sorted(_UNIT_MS)}, got {unit!r}")
    group = parser.add_mutually_exclusive_group()
    actions = []
    for option_unit in ("ms", "s"):
        words = f"{help} [{option_unit}]"
        if isinstance(default, str):
            words += f" (default: {default})"
        action = group.add_argument(
            f"--{name}-{option_unit}", *(aliases if option_unit == "s" else ()), dest=dest, default=None,
            type=kind or positive_float, metavar=option_unit.upper(), action=_InUnit, help=words,
            multiply=_UNIT_MS[option_unit], divide=_UNIT_MS[unit])
        if callable(default):
            api_default(action, lambda factor=_UNIT_MS[unit] / _UNIT_MS[option_unit]: default() * factor)
        actions.append(action)
    return actions[0], actions[1]


# -- defaults owned by the library ----------------------------------------------------------
def default_of(owner: Any, name: str) -> Any:
    """The library's default of ``name``: a field of the dataclass ``owner``, or a parameter of the
    function ``owner``."""
    import dataclasses
    import inspect

    if dataclasses.is_dataclass(owner):
        field = owner.__dataclass_fields__[name]
        return field.default if field.default is not dataclasses.MISSING else field.default_factory()
    return inspect.signature(owner).parameters[name].default


def library_default(target: str, name: str) -> Callable[[], Any]:
    """A deferred :func:`default_of`: ``target`` is ``"module:attribute"``, imported only when the
    default is asked for (``--help``, or an option left out), so start-up loads no torch."""

    def default() -> Any:
        import importlib

        module, attribute = target.split(":")
        return default_of(getattr(importlib.import_module(module), attribute), name)

    return default


# -- parser and help ----------------------------------------------------------------------
def api_default(action: argparse.Action, source: Callable[[], Any]) -> argparse.Action:
    """Mark ``action`` (default None: "the library's") to show ``source()`` as its default in ``--help``.

    ``source`` is called only when the help is printed, so a default owned by a
    module that loads torch costs nothing at start-up.
    """
    action.api_default = source
    return action


def _shown(value: Any, metavar: object) -> str:
    if isinstance(value, (tuple, list)):
        return ("x" if metavar == "WxH" else ",").join(_shown(v, None) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10_000:
        return f"{value:,}"
    return str(value)


class HelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: VALUE)`` to each option's help, unless the help already names its default."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if not text or "default" in text.lower() or action.default is argparse.SUPPRESS:
            return text
        source = getattr(action, "api_default", None)
        if source is not None:
            value = source()
        elif action.default is None or action.default is False or not action.option_strings:
            return text
        else:
            value = action.default
        return f"{text} (default: {_shown(value, action.metavar).replace('%', '%%')})"


_NUMBER = r"(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
#: Arguments that are numbers, the first negative: ``-5``, ``-0.1,0,0``, ``-1e-3,2``.
_NEGATIVE_NUMBERS = re.compile(rf"^-{_NUMBER}(,[-+]?{_NUMBER})*$")


class ArgumentParser(argparse.ArgumentParser):
    """An ``argparse`` parser whose errors are one line (``PROG: error: MESSAGE (see PROG --help)``), exit 2.

    Shows the defaults in the help (:class:`HelpFormatter`) and accepts ``--debug`` (show tracebacks)
    wherever it stands on the command line; sub-parsers are of the same class. A parser's ``unknown_hints``
    (option -> sentence) add to the refusal of an option it does not take what to do instead (``cmax simulate
    --resume``: it resumes by itself).
    """

    #: What to do instead of an option this parser does not take, by option (added to its refusal).
    unknown_hints: dict[str, str] = {}

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        if isinstance(kwargs.get("description"), str):   # module docstrings: ``code`` reads as code in --help
            kwargs["description"] = kwargs["description"].replace("``", "")
        super().__init__(*args, **kwargs)
        # a value such as -0.1,0,0 (--omega) or -1e-3 is a value, not an unknown option: argparse's own
        # pattern takes only -5 and -.5, and said 'expected one argument' for the others
        self._negative_number_matcher = _NEGATIVE_NUMBERS
        self.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                          help=f"show the traceback of an error (also: {DEBUG_ENV}=1)")

    def parse_args(self, args=None, namespace=None):  # noqa: D102 (argparse API)
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:   # named by the sub-command they were given to (argparse named the top-level command)
            owner = next((action.choices.get(getattr(parsed, action.dest, None)) for action in self._actions
                          if isinstance(action, argparse._SubParsersAction)), None)
            parser = owner or self
            hints = [parser.unknown_hints[extra] for extra in dict.fromkeys(extras) if extra in parser.unknown_hints]
            parser.error(f"unrecognized arguments: {' '.join(extras)}" + "".join(f"; {hint}" for hint in hints))
        return parsed

    def error(self, message: str):  # noqa: D102 (argparse API)
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def one_line(error: BaseException | str) -> str:
    """The message of an error on one line (whitespace runs collapsed)."""
    text = " ".join(str(error).split())
    if isinstance(error, BaseException):
        if isinstance(error, MemoryError):
            return f"out of memory{': ' + text if text else ''}"
        if isinstance(error, OSError) and error.filename is not None and error.strerror:
            return f"{error.strerror}: {error.filename}"
        if not text or (isinstance(error, KeyError) and len(error.args) == 1):
            return f"{type(error).__name__}: {text}"
    return text


def run_main(parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], int | None] | None = None,
             argv: Sequence[str] | None = None, *, prog: Callable[[argparse.Namespace], str] | None = None) -> int:
    """Parse ``argv`` and run ``run(args)`` (or ``args.run``); returns the exit status.

    Bad arguments exit with status 2 from the parser (one line). A
    :data:`USER_ERRORS` exception of the command prints ``PROG: error: MESSAGE``
    on one line and returns 2; with ``--debug`` or ``CMAX_DEBUG=1`` it is
    raised instead (the full traceback). A warning of the library prints as
    ``PROG: warning: MESSAGE`` on one line (Python's format with ``--debug``). ``KeyboardInterrupt`` returns 130
    with one line; SIGTERM and SIGHUP run the same clean-up and return 143 / 129 with one line
    (:mod:`cmax._signals`). A closed stdout (``| head``) ends quietly with status 1. Any other exception is a
    bug and keeps its traceback. With ``argv`` None (the process's own command line: the console script,
    ``python -m``), Ctrl-C, SIGTERM and SIGHUP are ignored once the command has ended, so that the process exits
    with the status returned here (:func:`cmax._signals.ignore_while_exiting`), not killed by a signal.
    """
    args = parser.parse_args(None if argv is None else [str(a) for a in argv])
    status = _run_command(parser, run, args, prog=prog)
    if argv is None:
        ignore_while_exiting()
    return status


def _run_command(parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], int | None] | None,
                 args: argparse.Namespace, *, prog: Callable[[argparse.Namespace], str] | None = None) -> int:
    """:func:`run_main`'s run of the parsed ``args``; returns the exit status."""
    command = run if run is not None else getattr(args, "run", None)
    label = prog(args) if prog is not None else parser.prog
    if command is None:
        parser.print_help(sys.stderr)
        return 2
    debug = bool(getattr(args, "debug", False)) or os.environ.get(DEBUG_ENV, "") not in ("", "0")
    try:
        with warnings.catch_warnings():
            if not debug:   # a warning of the library: one line, no source file and line of code
                warnings.showwarning = lambda message, *_, **__: print(
                    f"{label}: warning: {one_line(str(message))}", file=sys.stderr)
            with sigterm_as_interrupt():
                status = int(command(args) or 0)
            if (signum := terminated_by()) is not None and status != 128 + signum:   # 143 / 129: said so itself
                raise Terminated(signum)   # one whose exception Python dropped (in a finalizer) still ends the run
            return status
    except BrokenPipeError:  # the reader of stdout left (cmax info ... | head): not an error of the input
        if debug:
            raise
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 1
    except USER_ERRORS as error:
        if debug:
            raise
        print(f"{label}: error: {one_line(error)}", file=sys.stderr)
        return 2
    except Terminated as stop:
        if debug:
            raise
        print(f"{label}: terminated ({stop.name})", file=sys.stderr)
        return stop.status
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{label}: interrupted", file=sys.stderr)
        return 130

