"""What the representations share: input checks, windows, flat indices, chunking.

Events come as :class:`~cmax.events.Events` (numpy) or
:class:`~cmax.events.EventTensors` (torch); :func:`_inspect` validates them and
tells which. Sums over pixels go through the flat index ``(p*H + y)*W + x``
into a (2, H, W) array, computed in passes of at most ``_CHUNK`` events: the
one setting that every representation's chunked loop reads (from this module,
at call time).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Iterator, Union

import numpy as np

from cmax._jit import kernel

from cmax.events import Events, EventTensors, conversion_hint, polarity_hint

if TYPE_CHECKING:  # pragma: no cover
    import torch

EventsLike = Union[Events, EventTensors]
Array = Union[np.ndarray, "torch.Tensor"]

#: Events per vectorised pass (numpy, and torch on the CPU): temporaries of a few MB stay in
#: cache and are reused, where each (N,) temporary would be a fresh, page-faulting allocation.
_CHUNK = 1 << 20


#: Most elements of one output (4 GiB of float32): larger grids (absurd ``bins`` or sensor
#: sizes) raise :class:`ValueError` before anything is allocated.
MAX_OUTPUT_ELEMENTS = 1 << 30


# -- validation ----------------------------------------------------------------------------
def _check_output_size(shape: tuple[int, ...], what: str) -> None:
    """Raise :class:`ValueError` naming ``what`` when an output of ``shape`` would be absurd."""
    elements = 1
    for size in shape:
        elements *= int(size)
    if elements > MAX_OUTPUT_ELEMENTS:
        raise ValueError(
            f"{what}: an output of shape {tuple(int(v) for v in shape)} ({elements:,} values) exceeds "
            f"cmax.representations._common.MAX_OUTPUT_ELEMENTS={MAX_OUTPUT_ELEMENTS:,}"
        )


def _check_int(name: str, value: object, *, minimum: int | None = None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r} ({type(value).__name__})")
    if minimum is not None and int(value) < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def _check_optional_time(name: str, value: object) -> int | None:
    if value is None:
        return None
    if isinstance(value, (float, np.floating)) and float(value).is_integer():
        value = int(value)
    return _check_int(f"{name} (integer microseconds)", value)


def _stats_torch(events: EventTensors) -> tuple[int, int] | None:
    """Validate tensors; return (t_min, t_max) in µs, or None when there are no events.

    Costs one device synchronisation (bounds of x, y, t and whether p holds {0, 1}, {-1, +1} or bool,
    read back at once).
    """
    import torch

    for name in "xytp":
        column = getattr(events, name)
        if not isinstance(column, torch.Tensor):
            raise TypeError(f"events.{name} must be a torch.Tensor, got {type(column).__name__}")
        if column.ndim != 1:
            raise ValueError(f"events.{name} must have shape (N,), got {tuple(column.shape)}")
    for name in "xyt":
        dtype = getattr(events, name).dtype
        if dtype.is_floating_point or dtype.is_complex or dtype == torch.bool:
            raise TypeError(f"events.{name} must be an integer tensor, got {dtype}")
    if events.p.dtype.is_complex:
        raise TypeError(f"events.p must be integer, bool or real, got {events.p.dtype}")
    lengths = {name: getattr(events, name).shape[0] for name in "xytp"}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"events.x, y, t and p must have the same length, got {lengths}")
    devices = {str(getattr(events, name).device) for name in "xytp"}
    if len(devices) != 1:
        raise ValueError(f"events.x, y, t and p must be on one device, got {sorted(devices)}")
    _check_int("events.width", events.width, minimum=1)
    _check_int("events.height", events.height, minimum=1)
    if lengths["t"] == 0:
        return None
    bounds = [b.to(torch.int64) for name in "xyt" for b in torch.aminmax(getattr(events, name))]
    x_lo, x_hi, y_lo, y_hi, t_lo, t_hi, p_ok = torch.stack([*bounds, _polarity_ok(events.p)]).tolist()
    width, height = events.width, events.height
    swapped = (width != height and min(x_lo, y_lo) >= 0 and x_hi < height and y_hi < width)
    for name, low, high, size in (("x", x_lo, x_hi, width), ("y", y_lo, y_hi, height)):
        if low < 0 or high >= size:
            raise ValueError(f"events.{name} must lie in [0, {size}), got values in [{low}, {high}]" + (
                f"; every event lies inside a {height}x{width} sensor: width and height swapped? (EventTensors "
                f"takes width={height}, height={width} for them: an image's shape is (height, width), tonic's "
                "sensor_size (width, height, polarities))" if swapped else ""))
    if not p_ok:
        _refuse_polarity("events.p", events.p)
    _check_not_nanoseconds(t_lo, t_hi)
    return t_lo, t_hi


def _check_not_nanoseconds(t_lo: int, t_hi: int) -> None:
    """Refuse torch times from ``t_lo`` to ``t_hi`` (int, µs, as :class:`~cmax.events.EventTensors` states) that
    lie after the year 2100 as µs since 1970 and are nanoseconds since 1970 if anything (tonic's or a ROS export's
    int64 ns), as :class:`~cmax.events.Events` refuses them (:func:`cmax.io._checks.check_not_nanoseconds`), with
    a :class:`ValueError` naming ``events.t``. The implied-rate check of ``Events`` is not applied: tensors have
    no ``time_unit=`` through which a simulation's burst, accepted by ``Events(..., time_unit='us')``, could pass.
    """
    from cmax.io._checks import check_not_nanoseconds

    try:
        check_not_nanoseconds(max(t_lo, t_hi, key=abs), "events.t")
    except ValueError as error:         # a FormatError names a file; these are the caller's tensors
        raise ValueError(str(error)) from None


def _polarity_ok(p: "torch.Tensor") -> "torch.Tensor":
    """0-d int64 tensor on ``p``'s device: 1 when ``p`` holds polarities in one encoding, {0, 1} or {-1, +1}
    (bool: always), else 0. Unsigned integers take {0, 1} only (``uint8 255 == -1`` is true in torch)."""
    import torch

    if p.dtype == torch.bool:
        return torch.ones((), dtype=torch.int64, device=p.device)
    binary = ((p == 0) | (p == 1)).all()
    if p.dtype.is_signed:
        binary |= ((p == -1) | (p == 1)).all()
    return binary.to(torch.int64)


def _refuse_polarity(name: str, p: "torch.Tensor") -> None:
    """ValueError naming ``name`` and (up to ten of) the values of ``p`` that fit neither encoding."""
    import torch

    values = torch.unique(p).tolist()
    shown = values[:10] + (["..."] if len(values) > 10 else [])
    raise ValueError(f"{name} must hold polarities as {{0, 1}}, {{-1, +1}} or bool; got the values {shown}"
                     f"{polarity_hint(values)}")


def _inspect(events: object) -> tuple[str, tuple[int, int] | None]:
    """('numpy' | 'torch', (t_min, t_max) or None if empty) for validated events."""
    if isinstance(events, Events):
        return "numpy", ((int(events.t[0]), int(events.t[-1])) if len(events) else None)
    if isinstance(events, EventTensors):
        return "torch", _stats_torch(events)
    raise TypeError(
        "events must be cmax.Events (numpy) or cmax.EventTensors (torch, from "
        f"Events.to_torch()), got {type(events).__name__}{conversion_hint(events)}"
    )


# -- flat indices ----------------------------------------------------------------------------
def _chunks(start: int, stop: int) -> Iterator[slice]:
    """Consecutive slices of at most ``_CHUNK`` events covering ``[start, stop)``."""
    return (slice(i, min(i + _CHUNK, stop)) for i in range(start, stop, _CHUNK))


def _index_numpy(events: Events, run: slice, out: np.ndarray) -> np.ndarray:
    """``(p*H + y)*W + x`` of ``events[run]``, the flat index into (2, H, W), written into ``out``."""
    index = out[: run.stop - run.start]
    np.multiply(events.p[run], events.height, out=index, dtype=np.intp)
    index += events.y[run]
    index *= events.width
    index += events.x[run]
    return index


@kernel
def _count_pixels(x, y, p, width, height, counts):
    """Add one to ``counts[(p*H + y)*W + x]`` per event (a compiled loop, no index array)."""
    for i in range(x.size):
        counts[(np.intp(p[i]) * height + y[i]) * width + x[i]] += 1


def _pixel_counts(events: Events, dtype: type = np.int64) -> np.ndarray:
    """Events per (polarity, pixel): ``dtype`` (int64 or float32, exact to 2**24), shape (2 * H * W,)."""
    counts = np.zeros(2 * events.width * events.height, dtype)
    _count_pixels(events.x, events.y, events.p, events.width, events.height, counts)
    return counts


def _on_torch(p: "torch.Tensor") -> "torch.Tensor":
    """ON mask (bool) from int {0, 1}, bool, or signed float {-1, +1} polarity."""
    import torch

    return p if p.dtype == torch.bool else p > 0


def _index_torch(events: EventTensors) -> "torch.Tensor":
    """``(on*H + y)*W + x`` as int64, shape (N,): the flat index into (2, H, W)."""
    import torch

    index = _on_torch(events.p).to(torch.int64).mul_(events.height).add_(events.y)
    return index.mul_(events.width).add_(events.x)
