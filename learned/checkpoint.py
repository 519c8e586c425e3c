"""Checkpoints: model, optimiser, step, config and every RNG state, written atomically, read without running code.

A checkpoint is a ``torch.save`` of plain data only: tensors, and dicts, lists
and tuples of str, int, float, bool and None (the config as
:meth:`learned.config.Config.to_dict` gives it, the RNG states as tensors and
numbers). :func:`load_checkpoint` reads it with ``torch.load(weights_only=True)``,
which refuses any pickled object that would need code to rebuild (a
``__reduce__`` calling ``os.system``, a NumPy array, an arbitrary class): such
a file raises :class:`CheckpointError` before anything in it runs.

Checkpoints of earlier versions (format 1) stored NumPy's RNG state as a
pickled array and are refused the same way. A checkpoint you wrote yourself and
trust can be converted once, explicitly::

    python -m learned.checkpoint upgrade OLD.pt NEW.pt --trust-this-file

which is the one place that unpickles with ``weights_only=False`` (it runs any
code the file holds: never use it on a file from elsewhere).
"""
from __future__ import annotations

import argparse
import os
import pickle
import random
import re
import sys
import warnings
import zipfile
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from cmax.io.atomic import AtomicOutput, write_with

__all__ = ["CheckpointError", "FORMAT", "rng_state", "set_rng_state", "plain_data", "nonfinite_tensors",
           "save_checkpoint", "load_checkpoint", "check_weights", "upgrade_checkpoint", "main"]

#: Format of the checkpoints this version writes (stored under ``"format"``).
FORMAT = 2
_KEYS = {"model", "optimizer", "step", "config", "rng"}


class CheckpointError(ValueError):
    """A file is not a checkpoint this version can load safely (foreign, corrupt, old or crafted)."""


def rng_state() -> dict[str, Any]:
    """The states of Python's, NumPy's and torch's global generators, as plain data (tensors, tuples, numbers)."""
    numpy_state = np.random.get_state(legacy=False)
    if numpy_state["bit_generator"] != "MT19937":  # np.random's global generator is always MT19937
        raise ValueError(f"unexpected NumPy bit generator {numpy_state['bit_generator']!r}")
    return {
        "python": random.getstate(),
        "numpy": {"bit_generator": "MT19937",
                  "key": torch.from_numpy(numpy_state["state"]["key"].astype(np.int64)),
                  "pos": int(numpy_state["state"]["pos"]), "has_gauss": int(numpy_state["has_gauss"]),
                  "gauss": float(numpy_state["gauss"])},
        "torch": torch.get_rng_state(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore the generators from ``state``, as :func:`rng_state` returns it."""
    random.setstate(state["python"])
    saved = state["numpy"]
    np.random.set_state({"bit_generator": saved["bit_generator"],
                         "state": {"key": np.asarray(saved["key"], dtype=np.int64).astype(np.uint32),
                                   "pos": int(saved["pos"])},
                         "has_gauss": int(saved["has_gauss"]), "gauss": float(saved["gauss"])})
    torch.set_rng_state(state["torch"])


def plain_data(value: Any, where: str = "config") -> Any:
    """``value`` as plain data: dicts with str keys, lists, tuples, str, int, float, bool, None.

    Paths become str and NumPy scalars Python numbers; anything else raises TypeError
    naming where it sits (a checkpoint must load with ``weights_only=True``).
    """
    if isinstance(value, np.generic) and value.ndim == 0 and value.dtype.kind in "biuf":
        return value.item()          # before the plain types: np.float64 is a float subclass
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, dict):
        if not all(isinstance(key, str) for key in value):
            raise TypeError(f"{where}: keys must be str, got {sorted(map(repr, value))}")
        return {key: plain_data(item, f"{where}.{key}") for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        items = [plain_data(item, f"{where}[{i}]") for i, item in enumerate(value)]
        return items if isinstance(value, list) else tuple(items)
    raise TypeError(f"{where}: {type(value).__name__} cannot be stored in a checkpoint (plain data only)")


def nonfinite_tensors(state: dict[str, torch.Tensor]) -> list[str]:
    """The names of the floating-point tensors of ``state`` (a ``state_dict``) that hold a NaN or an infinity,
    in ``state``'s order (integer tensors, e.g. a step counter, are never non-finite; entries that are not
    tensors are left to the caller).

    >>> import torch
    >>> nonfinite_tensors({"a": torch.ones(2), "b": torch.tensor([1.0, float("nan")]), "n": torch.tensor(3)})
    ['b']
    """
    return [name for name, tensor in state.items() if isinstance(tensor, torch.Tensor) and
            (tensor.is_floating_point() or tensor.is_complex()) and not bool(torch.isfinite(tensor).all())]


def _nonfinite_message(bad: Sequence[str], total: int) -> str:
    return (f"{len(bad)} of its {total} weight tensors hold NaN or infinite values (e.g. {bad[0]}): the training "
            "run that wrote them diverged")


def save_checkpoint(path: str | Path, payload: dict[str, Any], *, overwrite: bool = True) -> Path:
    """``torch.save`` through :func:`cmax.io.atomic.write_with` (a lock, a private ``O_EXCL | O_NOFOLLOW``
    temporary file, fsync, rename): never a partial file under ``path``, never a planted link followed.

    ``payload`` needs the keys ``model``, ``optimizer``, ``step``, ``config``, ``rng``; its
    ``config`` is stored through :func:`plain_data` and ``format`` is set to :data:`FORMAT`. Weights that hold
    a NaN or an infinity (:func:`nonfinite_tensors`) raise ValueError and write nothing: a diverged run never
    replaces a good checkpoint. A write error (a full disk, a file-size limit) is an :class:`OSError` naming
    ``path`` (the temporary file removed), also where ``torch.save`` hid it behind a RuntimeError of its zip writer.
    With ``overwrite=False`` an existing ``path`` raises :class:`FileExistsError` (checked again at the rename).
    """
    missing = _KEYS - set(payload)
    if missing:
        raise ValueError(f"a checkpoint needs the keys {sorted(_KEYS)}, missing {sorted(missing)}")
    if isinstance(payload["model"], dict) and (bad := nonfinite_tensors(payload["model"])):
        raise ValueError(f"{path} was not written: {_nonfinite_message(bad, len(payload['model']))}")
    payload = {**payload, "config": plain_data(payload["config"]), "format": FORMAT}
    optimizer = payload["optimizer"]
    if isinstance(optimizer, dict) and "param_groups" in optimizer:   # hyper-parameters as plain numbers
        payload["optimizer"] = {**optimizer, "param_groups": plain_data(optimizer["param_groups"])}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def fill(output: AtomicOutput) -> None:
        with os.fdopen(os.dup(output.fd), "wb") as file:
            try:
                torch.save(payload, file)
            except RuntimeError as error:   # torch's zip writer failing to end after a failed write (a full disk,
                if isinstance(error.__context__, OSError):   # a file-size limit): that write's error, which
                    raise error.__context__ from None         # write_with reports naming the path
                raise

    return write_with(path, fill, overwrite=overwrite)


#: What ``torch.load`` raises for a file that is not a whole checkpoint (truncated, empty, foreign, crafted); an
#: OSError too (``[Errno 22] Invalid argument`` from a zip whose directory points past the end of a truncated file).
_LOAD_ERRORS = (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, TypeError, AttributeError, KeyError,
                ImportError, IndexError, zipfile.BadZipFile, UnicodeDecodeError, MemoryError, OverflowError, OSError)


def _refused(path: Path, error: BaseException) -> CheckpointError:
    detail = " ".join(str(error).split())
    # torch names the offending global ("... unsupported GLOBAL posix.system whose module ...").
    found = re.search(r"GLOBAL ([\w.]+)", detail) if isinstance(error, pickle.UnpicklingError) else None
    if found:
        return CheckpointError(
            f"{path} was refused: loading it would run code (it calls {found.group(1)}); "
            "a checkpoint of this version holds tensors and plain data only. If it is a checkpoint of an earlier "
            "version that you wrote yourself, convert it once with 'python -m learned.checkpoint upgrade OLD NEW "
            "--trust-this-file'")
    if isinstance(error, pickle.UnpicklingError) and "WeightsUnpickler error:" in detail:
        reason = detail.split("WeightsUnpickler error:", 1)[1].split(" Check the documentation")[0].strip()
        return CheckpointError(f"{path} is not a learned checkpoint (refused by the safe loader: {reason[:200]})")
    short = _cut_short(path)
    return CheckpointError(f"{path} is not a learned checkpoint{': ' + short if short else ''} "
                           f"(torch.load: {type(error).__name__}: {detail[:200]})")


def _cut_short(path: Path) -> str | None:
    """Why the file at ``path`` is not whole, when it is plainly cut short: empty, or the start of a zip archive
    (``torch.save``'s format) without the directory a zip ends with (a copy, download or save that stopped part-way:
    a full disk, a killed ``cp``); None otherwise."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as file:
            head = file.read(4)
        whole = zipfile.is_zipfile(path)
    except OSError:
        return None
    if size == 0:
        return "the file is empty (0 bytes)"
    if head == b"PK\x03\x04" and not whole:
        return (f"it is cut short: its {size:,} bytes begin as torch.save's zip archive but end before the "
                "archive's directory (a copy, download or save that did not finish?)")
    return None


def _tensors_where(value: Any, test: Callable[[torch.Tensor], bool],
                   where: str = "") -> list[tuple[str, torch.Tensor]]:
    """``(where, tensor)`` for each tensor in ``value`` (nested dicts, lists, tuples) for which ``test`` is true,
    ``where`` its path (``b[1]``, ``state.0.exp_avg``).

    >>> [name for name, _ in _tensors_where({"a": torch.ones(2), "b": [torch.zeros(1)]}, lambda t: not t.any())]
    ['b[0]']
    """
    if isinstance(value, torch.Tensor):
        return [(where, value)] if test(value) else []
    if isinstance(value, dict):
        items = ((f"{where}.{key}" if where else str(key), item) for key, item in value.items())
    elif isinstance(value, (list, tuple)):
        items = ((f"{where}[{i}]", item) for i, item in enumerate(value))
    else:
        return []
    return [found for name, item in items for found in _tensors_where(item, test, name)]


def _inflated_tensors(value: Any) -> list[tuple[str, torch.Tensor]]:
    """``(where, tensor)`` for each tensor in ``value`` (nested dicts, lists, tuples) whose numbers do not fit in its
    own storage: a view with zero or overlapping strides, which a file of a few kB can make claim 10^12 numbers
    that any elementwise check (``torch.isfinite``) or copy would then allocate. ``torch.save`` of a checkpoint's
    contiguous weights writes none.

    >>> [name for name, _ in _inflated_tensors({"a": torch.ones(3), "b": [torch.ones(4)[:2], torch.zeros(1).expand(9)]})]
    ['b[1]']
    """
    return _tensors_where(value, lambda t: t.numel() * t.element_size() > t.untyped_storage().nbytes())


def _unusual_tensors(value: Any) -> list[tuple[str, torch.Tensor]]:
    """``(where, tensor)`` for each tensor in ``value`` (nested dicts, lists, tuples) that is not a dense (strided)
    tensor: a sparse one, which ``torch.load(weights_only=True)`` rebuilds, has no storage to check and made the
    checks and ``load_state_dict`` fail with a traceback (NotImplementedError).

    >>> [name for name, _ in _unusual_tensors({"a": torch.ones(2), "b": [torch.eye(2).to_sparse()]})]
    ['b[0]']
    """
    return _tensors_where(value, lambda t: t.layout != torch.strided)


#: A checkpoint's zip entries may expand to at most this many times the file's size (plus
#: :data:`_EXPANSION_SLACK` bytes): ``torch.save`` stores them uncompressed, so a real checkpoint expands to about
#: its own size, and a crafted one of compressed zeros to hundreds of times it.
_MAX_EXPANSION = 2
_EXPANSION_SLACK = 1 << 20


def _check_expansion(path: Path) -> None:
    """Refuse a zip checkpoint whose entries, as its directory declares them, expand to far more than the file's
    size (compressed storages: a 250 kB file holding 200 MB of zeros), before ``torch.load`` allocates them."""
    try:
        with zipfile.ZipFile(path) as archive:
            declared = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, OSError, ValueError):   # not a zip (torch's legacy format, or no checkpoint at all):
        return                                          # torch.load says what it is
    size = path.stat().st_size
    if declared > _MAX_EXPANSION * size + _EXPANSION_SLACK:
        raise CheckpointError(f"{path} was refused: its zip entries expand to {declared:,} bytes from a file of "
                              f"{size:,} (compressed; torch.save stores them as they are): a crafted file that "
                              "would fill the memory")


def _check_payload(path: Path, payload: object) -> dict[str, Any]:
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path} is not a learned checkpoint (it holds a {type(payload).__name__}, not a dict)")
    missing = _KEYS - set(payload)
    if missing:
        raise CheckpointError(f"{path} is not a learned checkpoint (missing {sorted(missing)})")
    if payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} has checkpoint format {payload.get('format', 1)!r}, this version reads "
                              f"{FORMAT}; convert a trusted one with 'python -m learned.checkpoint upgrade'")
    model = payload["model"]
    if not (isinstance(model, dict) and all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                            for k, v in model.items())):
        raise CheckpointError(f"{path}: 'model' must map parameter names to tensors")
    unusual = _unusual_tensors(payload)
    if unusual:
        name, tensor = unusual[0]
        raise CheckpointError(f"{path} was refused: {len(unusual)} of its tensors are not dense (e.g. {name}: "
                              f"{tensor.layout}); torch.save of a checkpoint's weights, optimizer and RNG states "
                              "writes dense tensors only")
    inflated = _inflated_tensors(payload)
    if inflated:
        name, tensor = inflated[0]
        raise CheckpointError(
            f"{path} was refused: {len(inflated)} of its tensors claim more numbers than the file stores (e.g. "
            f"{name}: {tensor.numel():,} numbers over {tensor.untyped_storage().nbytes():,} bytes of storage, a "
            "repeating view); torch.save writes no such tensor: a crafted file that would fill the memory")
    bad = nonfinite_tensors(model)
    if bad:
        raise CheckpointError(f"{path} was refused: {_nonfinite_message(bad, len(model))}; use an earlier checkpoint")
    step = payload["step"]
    if not (isinstance(step, int) and not isinstance(step, bool) and step >= 0):
        raise CheckpointError(f"{path}: 'step' must be an integer >= 0, got {step!r}")
    if not isinstance(payload["config"], dict):
        raise CheckpointError(f"{path}: 'config' must be a dict, got {type(payload['config']).__name__}")
    if not (isinstance(payload["optimizer"], dict) and isinstance(payload["rng"], dict)):
        raise CheckpointError(f"{path}: 'optimizer' and 'rng' must be dicts")
    return payload


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` without running any code it may hold.

    Raises
    ------
    FileNotFoundError
        No file at ``path``.
    CheckpointError (a ValueError)
        Not a regular file (a device, a FIFO), not a ``torch.save`` file, a pickle that needs code to load (crafted, or
        of format 1: see :func:`upgrade_checkpoint`), keys of the wrong kind, or weights that hold a NaN or
        an infinity (a diverged run's).
    """
    path = Path(path)
    if path.is_dir():
        inside = sorted(path.glob("*.pt"))
        hint = f"give the file, e.g. {path / 'last.pt' if (path / 'last.pt').is_file() else inside[0]}" if inside \
            else "it holds no .pt file"
        raise FileNotFoundError(f"no checkpoint at {path}: it is a folder ({hint})")
    if not path.is_file():
        if path.exists():   # a device (a link to /dev/zero), a FIFO, a socket: exists, holds no file
            raise CheckpointError(f"{path} is not a regular file (a device, a pipe or a socket): give a checkpoint "
                                  "file of learned.train (e.g. runs/teacher/last.pt)")
        raise FileNotFoundError(f"no checkpoint at {path}")
    _check_expansion(path)
    try:
        with warnings.catch_warnings():  # e.g. torch's note on an unusual pickle protocol
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except _LOAD_ERRORS as error:
        raise _refused(path, error) from None
    return _check_payload(path, payload)


def _kind(tensor: torch.Tensor) -> str:
    """The kind of number a tensor holds, as :func:`check_weights` compares them: ``"real floating point"`` (any
    precision: a float16 or float64 copy of float32 weights loads the same), ``"integer"``, ``"bool"`` or
    ``"complex"`` (``load_state_dict`` would cast the others silently: a complex weight losing its imaginary part,
    a bool weight becoming 0 or 1)."""
    if tensor.is_complex():
        return "complex"
    if tensor.is_floating_point():
        return "real floating point"
    return "bool" if tensor.dtype == torch.bool else "integer"


def check_weights(model_config: Any, state: dict[str, torch.Tensor], source: str | Path) -> None:
    """Refuse weights that do not fit the network of ``model_config`` before that network is built.

    The network (:class:`learned.model.DepthPoseNet`) is built on torch's ``meta`` device, which
    allocates no memory, and the name and shape of each of its parameters and buffers is compared with
    ``state`` (a checkpoint's ``"model"``): a crafted config (``model.levels=24`` beside small weights) would
    otherwise allocate many GB before its weights were checked. The kind of number of each tensor is compared
    too (:func:`_kind`: real floating point of any precision, integer, bool, complex). Raises
    :class:`CheckpointError` (one line, naming ``source``) on a mismatch or on a network that torch cannot even
    describe.

    >>> from learned.model import DepthPoseNet, ModelConfig
    >>> check_weights(ModelConfig(width=2, levels=1), DepthPoseNet(ModelConfig(width=2, levels=1)).state_dict(), "x")
    >>> try:
    ...     check_weights(ModelConfig(width=2, levels=9), DepthPoseNet(ModelConfig(width=2, levels=1)).state_dict(),
    ...                   "x.pt")
    ... except CheckpointError as error:
    ...     print(str(error)[:47])
    x.pt: its weights do not fit its model config (
    """
    from learned.model import DepthPoseNet

    try:
        with torch.device("meta"):
            network = DepthPoseNet(model_config).state_dict()
        expected = {name: tuple(tensor.shape) for name, tensor in network.items()}
    except (RuntimeError, ValueError, OverflowError, MemoryError) as error:   # sizes past int64
        raise CheckpointError(f"{source}: its model config describes a network torch cannot build "
                              f"({' '.join(str(error).split())[:200]})") from None
    stored = {name: tuple(tensor.shape) for name, tensor in state.items()}
    missing = sorted(set(expected) - set(stored))
    unexpected = sorted(set(stored) - set(expected))
    other = [name for name in expected if name in stored and stored[name] != expected[name]]
    kinds = [name for name in expected if name in state and _kind(state[name]) != _kind(network[name])]
    if not (missing or unexpected or other or kinds):
        return
    parts = [f"{len(missing)} of its {len(expected)} tensors missing (e.g. {missing[0]})" if missing else "",
             f"{len(unexpected)} unexpected (e.g. {unexpected[0]})" if unexpected else "",
             f"{len(other)} of another shape (e.g. {other[0]}: {list(stored[other[0]])}, the config's "
             f"{list(expected[other[0]])})" if other else "",
             f"{len(kinds)} of another kind of number (e.g. {kinds[0]}: {state[kinds[0]].dtype}, the network's "
             f"{_kind(network[kinds[0]])})" if kinds else ""]
    raise CheckpointError(f"{source}: its weights do not fit its model config ({'; '.join(p for p in parts if p)})")


def _upgraded_rng(rng: dict[str, Any]) -> dict[str, Any]:
    numpy_state = rng["numpy"]
    if isinstance(numpy_state, tuple):  # format 1: np.random.get_state()
        name, key, pos, has_gauss, gauss = numpy_state
        numpy_state = {"bit_generator": str(name), "key": torch.from_numpy(np.asarray(key).astype(np.int64)),
                       "pos": int(pos), "has_gauss": int(has_gauss), "gauss": float(gauss)}
    return {"python": rng["python"], "numpy": numpy_state, "torch": rng["torch"]}


def upgrade_checkpoint(old: str | Path, new: str | Path, *, trust: bool = False, overwrite: bool = False) -> Path:
    """Convert a TRUSTED checkpoint of format 1 to the current format (plain data, loads with ``weights_only=True``).

    This unpickles ``old`` with ``weights_only=False``, which runs any code the file
    holds: pass ``trust=True`` only for a file you wrote yourself. A file that is not a whole checkpoint
    (truncated, empty) raises :class:`CheckpointError` in one line naming it. An existing ``new`` (``old`` itself
    too) raises :class:`FileExistsError` before ``old`` is read, unless ``overwrite=True``.
    """
    if trust is not True:
        raise ValueError("upgrade_checkpoint unpickles the file with weights_only=False, which runs any code it "
                         "holds: pass trust=True (--trust-this-file) only for a checkpoint you wrote yourself")
    old, new = Path(old), Path(new)
    if not old.is_file():
        raise FileNotFoundError(f"no checkpoint at {old}")
    if os.path.lexists(new) and not overwrite:
        same = " (the checkpoint being converted: its format-1 original would be gone)" if new.exists() and \
            os.path.samefile(old, new) else ""
        raise FileExistsError(f"{new} exists{same}: --overwrite replaces it, or give another NEW")
    try:
        payload = torch.load(old, map_location="cpu", weights_only=False)
    except _LOAD_ERRORS as error:   # truncated, empty, not a torch.save file
        raise CheckpointError(f"{old} is not a learned checkpoint (torch.load: {type(error).__name__}: "
                              f"{' '.join(str(error).split())[:200]})") from None
    if not isinstance(payload, dict) or _KEYS - set(payload):
        raise CheckpointError(f"{old} is not a learned checkpoint")
    payload = {**payload, "rng": _upgraded_rng(payload["rng"]), "step": int(payload["step"])}
    written = save_checkpoint(new, payload, overwrite=overwrite)
    load_checkpoint(written)  # proves it now loads safely
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m learned.checkpoint upgrade OLD NEW --trust-this-file``; ``argv``: the arguments (None: the
    command line's); returns the exit status."""
    from cmax._args import ArgumentParser, run_main

    parser = ArgumentParser(prog="python -m learned.checkpoint",
                            description="Convert a trusted checkpoint of an earlier version to the safe format.")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    upgrade = actions.add_parser("upgrade", help="rewrite OLD (format 1) as NEW (format 2)")
    upgrade.add_argument("old", type=Path, help="checkpoint of format 1 that you wrote yourself")
    upgrade.add_argument("new", type=Path, help="output path")
    upgrade.add_argument("--trust-this-file", action="store_true",
                         help="required: OLD is unpickled with weights_only=False and can run code")
    upgrade.add_argument("--overwrite", action="store_true", help="replace an existing NEW (else refused)")

    def run(args: argparse.Namespace) -> int:
        written = upgrade_checkpoint(args.old, args.new, trust=args.trust_this_file, overwrite=args.overwrite)
        print(f"wrote {written} (checkpoint format {FORMAT})")
        return 0

    return run_main(parser, run, argv)


if __name__ == "__main__":
    sys.exit(main())
