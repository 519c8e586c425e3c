"""The ESIM event model: events from a sequence of time-stamped frames.

Each pixel keeps a reference log intensity ``L_ref``, initialised to the
first frame. Between two samples the log intensity

    L = log(I / 255 + eps)                (I: 8-bit grey value in [0, 255])

is taken as linear in time. Every crossing of ``L_ref + k*Cp`` (ON) or
``L_ref - k*Cn`` (OFF), ``k = 1, 2, ...``, emits one event, time-stamped by
linear interpolation inside the interval, and moves ``L_ref`` by one
threshold. A pixel may fire several events per interval; they all have the
polarity of the change, since ``L`` is monotonic between two samples.

The arithmetic follows the reference C++ implementation (``esim_py`` of
uzh-rpg/rpg_vid2e) so that both give the same events on the same frames:

* ``L`` is float32: ``log(I * float32(1/255) + float32(eps))`` with OpenCV's
  own ``cv::log`` algorithm, reimplemented bit for bit in
  :mod:`cmax.sim._cvlog` (the ``cv2`` wheels call Intel IPP instead, which
  rounds differently). For uint8 frames a 256-entry table of these values
  is used; integer-valued float frames give the same values. Fractional grey
  values (frames interpolated by :mod:`cmax.sim.sampling`) use numpy's
  float32 log of the same argument, within 1-2 ulp of ``cv::log``: a bit-exact
  emulation costs far more and there is no reference to agree with.
* ``L_ref`` is a float32 value that moves one float32 threshold at a time
  (``L_ref += C`` in float32, sequentially). This matters: a pixel that
  returns to the grey value it started from lands *exactly* on a crossing
  level, and whether it fires depends on the float32 rounding of that sum.
  The sequential sums are computed rank by rank over the crossing pixels
  (:mod:`cmax.sim.crossings`).
* Crossing times are ``t0 + (level - L0) / (L1 - L0) * (t1 - t0)``, with the
  two differences in float32 and the rest in float64, then rounded to whole
  microseconds, half up: ``floor(tau + 0.5)``. A crossing therefore lies in
  ``[t0, t1]`` µs.

Events of one interval are ordered by time, ties by pixel in raster order
(row-major, ``y * width + x``), then by crossing order; this is a stable
version of the reference's ``std::sort`` by time. On the reference's own test
frames (``esim_truck_pan``, Cp = Cn = 0.2 and 0.1) the events agree one to
one with the C++ ESIM's, within 1 µs (``tests/test_sim_esim.py``).

Cost per frame (:meth:`EventSimulator.step`): a table look-up for the log
intensity, then one compiled pass (numba, :func:`cmax.sim.crossings._interval_crossings`)
over the sensor that finds the pixels within 10 % of a threshold of their next
level (a few percent of them on real video) and computes their crossings and
times, and a stable counting sort on time that writes the events, in order,
straight into the output columns (:meth:`simulate` fills one set of columns
frame after frame, with no concatenation at the end). With a refractory
period or shot noise the vectorised numpy path of :mod:`cmax.sim.crossings`
runs instead; both give the same events.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza. "ESIM: an Open Event Camera Simulator."
Conference on Robot Learning (CoRL), 2018.
https://proceedings.mlr.press/v87/rebecq18a.html
"""
from __future__ import annotations

import warnings

import cv2
import numpy as np

import cmax.events
from cmax.events import EventLimitError, Events
from cmax.sim._cvlog import _cv_log32f
from cmax.sim.crossings import (
    Crossings,
    _interval_crossings,
    crossing_bound,
    _sorted_by_time,
    crossing_times,
    fire,
    near_pixels,
    refractory_keep,
    sort_events,
    threshold_crossings,
)
from cmax.sim.esim_noise import leak_drift, leak_phase, shot_noise, threshold_map
from cmax.sim.esim_settings import (
    MIN_THRESHOLD,
    MIN_THRESHOLD_FRACTION,
    EsimSettings,
    _check_log_eps,
    _whole,
)

__all__ = [
    "MIN_THRESHOLD",
    "MIN_THRESHOLD_FRACTION",
    "Crossings",
    "EsimSettings",
    "EventSimulator",
    "log_intensity",
    "threshold_crossings",
    "unit_range_note",
]

_NEVER = np.iinfo(np.int64).min // 4  # last event time of a pixel that has not fired yet
_MAX_SENSOR_SIZE = 65535
_NEAR = np.float32(0.9)


# -- log intensity ----------------------------------------------------------------------
def _grey_frame(frame: object, name: str) -> np.ndarray:
    """(H, W) grey values as uint8 or float32 from a checked (H, W) or BGR (H, W, 3) frame."""
    array = np.asarray(frame)
    if array.dtype.kind == "b" or array.dtype.kind not in "uif":
        raise TypeError(f"{name} must hold grey values (uint8 or float), got dtype {array.dtype}")
    colour = array.ndim == 3 and array.shape[2] == 3
    if array.ndim != 2 and not colour:
        raise ValueError(f"{name} must have shape (H, W) or (H, W, 3) (BGR), got {array.shape}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"{name} must not be empty, got shape {array.shape}")
    if array.shape[0] > _MAX_SENSOR_SIZE or array.shape[1] > _MAX_SENSOR_SIZE:
        raise ValueError(f"{name} is larger than {_MAX_SENSOR_SIZE} pixels: {array.shape}")
    if array.dtype != np.uint8:
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise ValueError(f"{name} contains NaN or infinite values")
        low, high = array.min(), array.max()
        if low < 0 or high > 255:
            raise ValueError(f"{name} must hold grey values in [0, 255], got [{low}, {high}]")
        array = array.astype(np.uint8 if array.dtype.kind in "iu" else np.float32)
    if colour:
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_BGR2GRAY)
    return array


def unit_range_note(frame: np.ndarray, what: str = "frames") -> str | None:
    """The warning for float grey values that look like a [0, 1] image, or None.

    A float array whose values lie in [0, 1], not all zero and not all whole
    numbers (0/1 values are as likely a dark 8-bit frame): ESIM takes grey
    values in [0, 255], so to it such frames are nearly black.

    >>> import numpy as np
    >>> unit_range_note(np.array([[0.2, 0.9]], np.float32)) is not None, unit_range_note(np.array([[0.0, 1.0]]))
    (True, None)
    """
    if frame.dtype.kind != "f" or not frame.size:
        return None
    low, high = float(np.nanmin(frame)), float(np.nanmax(frame))
    if not (0 < high <= 1) or np.array_equal(frame, np.rint(frame)):
        return None
    return (f"{what} are floats in [{low:g}, {high:g}]: ESIM takes grey values in [0, 255], so to it the whole "
            "sequence is nearly black (a [0, 1] image? multiply it by 255)")


def _log_float32(grey: np.ndarray, log_eps: float) -> np.ndarray:
    """``cv::log(grey * float32(1/255) + float32(eps))`` in float32, same shape."""
    scaled = grey.astype(np.float32) * np.float32(1.0 / 255.0) + np.float32(log_eps)
    return _cv_log32f(scaled)


def _log_grey(grey: np.ndarray, log_eps: float, table: np.ndarray | None = None) -> np.ndarray:
    """Log of checked grey values (uint8 or float32), float32, same shape.

    Whole grey values take the 256-entry table of ``cv::log`` values (exactly
    the reference's); fractional ones (interpolated frames) numpy's float32
    log of the same argument, within an ulp or two of ``cv::log`` and far
    faster than its bit-exact emulation (:func:`_log_float32`).
    """
    table = _log_float32(np.arange(256, dtype=np.float32), log_eps) if table is None else table
    if grey.dtype == np.uint8:
        return cv2.LUT(grey, table)  # = table[grey], faster than numpy indexing
    whole = grey.astype(np.uint8)  # truncates; equal to grey where the value is whole
    exact = whole == grey
    if exact.all():
        return cv2.LUT(whole, table)
    out = np.log(grey * np.float32(1.0 / 255.0) + np.float32(log_eps), dtype=np.float32)
    np.copyto(out, cv2.LUT(whole, table), where=exact)
    return out


def log_intensity(frame: object, log_eps: float = 1e-3) -> np.ndarray:
    """Log intensity ``L = log(I/255 + eps)`` of one frame, as ESIM computes it.

    Parameters
    ----------
    frame : array_like, shape (H, W) or (H, W, 3)
        Grey values in [0, 255] (uint8, any integer type or float). Colour
        frames are taken as **BGR** (OpenCV's order, as read by
        ``cv2.VideoCapture``) and converted with ``cv2.COLOR_BGR2GRAY``.
    log_eps : float
        ``eps`` (> 0).

    Returns
    -------
    ndarray, shape (H, W), float32
        ``log(I * float32(1/255) + float32(eps))`` in float32, bit for bit as
        OpenCV's ``cv::log`` (see the module notes); a uint8 frame and the
        same values as floats give identical results.

    Examples
    --------
    >>> import numpy as np
    >>> log_intensity(np.full((2, 3), 255, np.uint8)).shape
    (2, 3)
    """
    log_eps = _check_log_eps(log_eps)
    return _log_grey(_grey_frame(frame, "frame"), log_eps)


# -- the simulator ----------------------------------------------------------------------
class EventSimulator:
    """ESIM (Rebecq et al., CoRL 2018): events from time-stamped frames.

    Parameters
    ----------
    cp, cn, threshold_sigma, refractory_us, log_eps, seed, shot_noise_rate_hz, leak_rate_hz
        See :class:`EsimSettings` (the thresholds are stored as float32).

    Notes
    -----
    :meth:`simulate` runs a whole sequence; :meth:`step` feeds one frame at a
    time and keeps the state in between (the first frame only initialises
    ``L_ref``); ``simulate(frames, t)`` equals the concatenated ``step`` calls
    of a fresh simulator. Frames are (H, W) grey or (H, W, 3) **BGR** values
    in [0, 255]; times are int64 microseconds. Noise events (shot noise) are
    added on top of the signal: they neither move ``L_ref`` nor count for
    the refractory period. Leak events come from the drifting reference and
    are ordinary crossings. The threshold map, leak phase and noise are drawn
    from one generator seeded by ``seed``; :meth:`reset` restarts it, so a
    simulator gives the same events every time it is run.

    Examples
    --------
    >>> import numpy as np
    >>> frames = np.stack([np.full((2, 2), v, np.uint8) for v in (50, 100, 50)])
    >>> events = EventSimulator(cp=0.2, cn=0.2).simulate(frames, np.array([0, 1000, 2000]))
    >>> len(events), int(events.p.sum()), events.t[:4].tolist()
    (24, 12, [290, 290, 290, 290])
    """

    def __init__(
        self,
        cp: float = 0.2,
        cn: float = 0.2,
        threshold_sigma: float = 0.0,
        refractory_us: int = 0,
        log_eps: float = 1e-3,
        seed: int | None = None,
        *,
        shot_noise_rate_hz: float = 0.0,
        leak_rate_hz: float = 0.0,
    ) -> None:
        self.settings = EsimSettings(
            cp, cn, threshold_sigma, refractory_us, log_eps, seed, shot_noise_rate_hz, leak_rate_hz
        )
        self._entropy = np.random.SeedSequence(self.settings.seed).entropy
        self._unit_warned = False  # the [0, 1]-image warning, given at most once per simulator
        self._table = _log_float32(np.arange(256, dtype=np.float32), self.settings.log_eps)
        self.reset()

    @classmethod
    def from_settings(cls, settings: EsimSettings) -> "EventSimulator":
        """A simulator with the given ``settings`` (:class:`EsimSettings`)."""
        if not isinstance(settings, EsimSettings):
            raise TypeError(f"settings must be EsimSettings, got {type(settings).__name__}")
        s = settings
        return cls(s.cp, s.cn, s.threshold_sigma, s.refractory_us, s.log_eps, s.seed,
                   shot_noise_rate_hz=s.shot_noise_rate_hz, leak_rate_hz=s.leak_rate_hz)

    def __repr__(self) -> str:
        return f"EventSimulator({self.settings})"

    # -- state ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all state; the next frame initialises the simulator again."""
        self._rng = np.random.default_rng(np.random.SeedSequence(self._entropy))
        self._shape: tuple[int, int] | None = None
        self._t_us = 0
        self._log = self._ref = self._last_t = None
        self._c_on: np.ndarray | np.float32 = np.float32(self.settings.cp)
        self._c_off: np.ndarray | np.float32 = np.float32(self.settings.cn)

    @property
    def initialized(self) -> bool:
        """Whether a first frame has been seen since construction or :meth:`reset`."""
        return self._shape is not None

    @property
    def t_us(self) -> int | None:
        """Time of the last frame in µs, or None before the first one."""
        return self._t_us if self.initialized else None

    @property
    def reference(self) -> np.ndarray | None:
        """The per-pixel reference log intensity ``L_ref``, (H, W) float32 (a copy), or None."""
        return None if self._ref is None else self._ref.reshape(self._shape).copy()

    def _initialize(self, log: np.ndarray, t_us: int) -> None:
        s, n = self.settings, log.size
        self._shape, self._t_us = log.shape, t_us
        self._log = log.ravel().copy()
        if s.threshold_sigma > 0:
            self._c_on = threshold_map(self._rng, s.cp, s.threshold_sigma, n)
            self._c_off = threshold_map(self._rng, s.cn, s.threshold_sigma, n)
        self._ref = self._log.copy()
        if s.leak_rate_hz > 0:  # random phase of the leak: L_ref in (L - Cp, L]
            self._ref = leak_phase(self._rng, self._ref, self._c_on)
        self._last_t = np.full(n, _NEVER, np.int64) if s.refractory_us > 0 else None
        self._derive()

    def state(self) -> dict[str, np.ndarray]:
        """Everything the simulator carries from one frame to the next, as arrays (copies), so that
        :meth:`restore` on a fresh simulator of the same settings continues exactly (the same events, bit for bit).

        Returns
        -------
        dict of str to ndarray
            ``shape`` (2,) int64 ``(H, W)``; ``t_us`` () int64, the last frame's time [µs]; ``log`` and
            ``reference`` (H*W,) float32, the last frame's log intensity and ``L_ref``; ``c_on``, ``c_off`` ()
            or (H*W,) float32, the thresholds [log intensity]; ``last_t`` (H*W,) int64 [µs] with a refractory
            period (else absent); ``rng`` () the JSON text of the noise generator's state. ValueError before
            the first frame (there is no state yet).
        """
        import json

        if not self.initialized:
            raise ValueError("the simulator has no state before its first frame")
        out = {"shape": np.array(self._shape, np.int64), "t_us": np.array(self._t_us, np.int64),
               "log": self._log.copy(), "reference": self._ref.copy(),
               "c_on": np.array(self._c_on, np.float32), "c_off": np.array(self._c_off, np.float32),
               "rng": np.array(json.dumps(self._rng.bit_generator.state))}
        if self._last_t is not None:
            out["last_t"] = self._last_t.copy()
        return out

    def restore(self, state: dict[str, np.ndarray]) -> None:
        """Continue from ``state`` (:meth:`state` of a simulator with the same settings): the next :meth:`step`
        gives the events that simulator's next step would.

        Parameters
        ----------
        state : dict of str to ndarray
            As :meth:`state` returns it (also read back from an ``.npz`` file): ``log``, ``reference`` (H*W,)
            float32 and the rest. A state of another sensor size, refractory setting or threshold mismatch than
            these settings raises ValueError.
        """
        import json

        s = self.settings
        try:
            height, width = (int(v) for v in np.asarray(state["shape"]).ravel())
            n = height * width
            arrays = {name: np.ascontiguousarray(state[name], dtype) for name, dtype in
                      (("log", np.float32), ("reference", np.float32), ("c_on", np.float32), ("c_off", np.float32))}
            last_t = state.get("last_t")
            rng = json.loads(str(np.asarray(state["rng"])))
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"not a simulator state: {error}") from None
        sizes = {name: array.size for name, array in arrays.items()}
        mismatch = s.threshold_sigma > 0
        if (sizes["log"] != n or sizes["reference"] != n or n == 0
                or {sizes["c_on"], sizes["c_off"]} != {n if mismatch else 1}
                or (last_t is None) != (s.refractory_us <= 0) or (last_t is not None and np.size(last_t) != n)):
            raise ValueError(f"the state does not fit these settings ({s}) on a {width}x{height} sensor")
        self.reset()
        self._rng.bit_generator.state = rng
        self._shape, self._t_us = (height, width), int(np.asarray(state["t_us"]))
        self._log, self._ref = arrays["log"].ravel().copy(), arrays["reference"].ravel().copy()
        self._c_on = arrays["c_on"].ravel().copy() if mismatch else np.float32(arrays["c_on"].ravel()[0])
        self._c_off = arrays["c_off"].ravel().copy() if mismatch else np.float32(arrays["c_off"].ravel()[0])
        self._last_t = None if last_t is None else np.ascontiguousarray(last_t, np.int64).ravel().copy()
        self._derive()

    def _derive(self) -> None:
        """The thresholds' derived forms and the pixel look-ups, from ``_c_on``, ``_c_off`` and ``_shape``."""
        self._near_on = _NEAR * self._c_on
        self._near_off = -_NEAR * self._c_off
        # the compiled kernel's form: float32 arrays of length 1 (one value) or N
        self._kernel_thresholds = tuple(
            np.atleast_1d(np.asarray(value, np.float32))
            for value in (self._c_on, self._c_off, self._near_on, self._near_off)
        )
        height, width = self._shape  # pixel index -> (x, y), looked up instead of divmod
        self._x_of = np.tile(np.arange(width, dtype=np.uint16), height)
        self._y_of = np.repeat(np.arange(height, dtype=np.uint16), width)

    # -- one interval ---------------------------------------------------------------------
    def _advance(self, log: np.ndarray, t_us: int, sink: "_Columns | None" = None) -> Events | None:
        """Events of the interval from the previous sample to ``log`` at ``t_us``.

        Without refractory period and shot noise one compiled pass over the
        sensor finds the crossings pixel by pixel and a counting sort on time
        writes them, in order, into ``sink`` (when given; returns None) or into
        fresh columns. Otherwise a few passes over the whole sensor find the
        near pixels and everything else works on those (see
        :mod:`cmax.sim.crossings`).
        """
        s = self.settings
        height, width = self._shape
        dt = t_us - self._t_us
        log1 = log.ravel()
        drift = None
        if s.leak_rate_hz > 0:  # crossings of L + drift against a fixed L_ref, then L_ref -= drift
            drift = leak_drift(s.leak_rate_hz, dt, self._c_on)
            log1 = (log1 + drift).astype(np.float32)
        if self._last_t is None and s.shot_noise_rate_hz <= 0:
            limit = int(cmax.events.MAX_EVENTS)
            pixel, t_rel, polarity, held, bound = _interval_crossings(
                self._ref, self._log, log1, *self._kernel_thresholds, dt, limit)
            if bound > limit:
                raise self._too_many(bound, limit, t_us)
            if not held:  # pragma: no cover - the bound has a margin of two levels
                raise RuntimeError("ESIM: more crossings than the bound allows (a bug)")
            if drift is not None:
                self._ref = (self._ref - drift).astype(np.float32)
            self._log, self._t_us = log.ravel(), t_us  # log is a fresh array, owned
            target = sink if sink is not None else _Columns(pixel.size)
            offset = target.reserve(pixel.size)
            _sorted_by_time(pixel, t_rel, polarity, dt, width, t_us - dt, *target.columns, offset)
            return None if sink is not None else target.events(width, height)
        events = self._advance_arrays(log, log1, t_us, dt, drift)
        if sink is None:
            return events
        sink.append(events)
        return None

    def _advance_arrays(self, log: np.ndarray, log1: np.ndarray, t_us: int, dt: int,
                        drift) -> Events:
        """:meth:`_advance` with refractory period or shot noise, on the near pixels."""
        s = self.settings
        height, width = self._shape
        log0, ref = self._log, self._ref  # ref (owned) moves in place
        rows = near_pixels(ref, log1, self._near_on, self._near_off)
        limit = int(cmax.events.MAX_EVENTS)
        bound = crossing_bound(rows, ref, log1, self._c_on, self._c_off)
        noise = s.shot_noise_rate_hz * height * width * dt * 1e-6  # the expected count of shot-noise events
        if bound + noise > limit:
            raise self._too_many(bound, limit, t_us, noise)
        refractory = self._last_t is not None
        pixel, level, polarity = fire(rows, ref, log0, log1, self._c_on, self._c_off,
                                      by_pixel=refractory)
        t_rel = crossing_times(pixel, level, log0, log1, dt)
        if refractory:
            keep = refractory_keep(pixel, self._t_us + t_rel, self._last_t, s.refractory_us)
            pixel, polarity, t_rel = pixel[keep], polarity[keep], t_rel[keep]
        if drift is not None:
            self._ref = (ref - drift).astype(np.float32)
        if s.shot_noise_rate_hz > 0:
            noise_pixel, noise_t, noise_p = shot_noise(self._rng, s.shot_noise_rate_hz,
                                                       height * width, dt)
            pixel = np.concatenate([pixel, noise_pixel])
            t_rel = np.concatenate([t_rel, noise_t])
            polarity = np.concatenate([polarity, noise_p])
        self._log, self._t_us = log.ravel(), t_us  # log is a fresh array, owned
        pixel, t_rel, polarity = sort_events(pixel, t_rel, polarity, height * width, dt)
        t_rel += t_us - dt
        return Events._trusted(self._x_of[pixel], self._y_of[pixel], t_rel, polarity, width, height)

    def _too_many(self, bound: int, limit: int, t_us: int, noise: float = 0.0) -> EventLimitError:
        """The error for an interval whose events could exceed ``limit`` (``bound`` crossings at most, ``noise``
        shot-noise events expected); nothing was changed."""
        height, width = self._shape
        seconds = (t_us - self._t_us) * 1e-6
        leak = self.settings.leak_rate_hz * seconds * height * width  # leak crossings, about
        for rate, count, name in ((self.settings.shot_noise_rate_hz, noise, "shot noise"),
                                  (self.settings.leak_rate_hz, leak, "leak events")):
            if count > limit / 2:
                return EventLimitError(
                    f"the interval from {self._t_us} µs to the frame at {t_us} µs is {seconds:g} s long: {name} of "
                    f"{rate:g} Hz per pixel over the {width}x{height} sensor add about {count:,.0f} events to it, "
                    f"more than cmax.events.MAX_EVENTS={limit:,} that fit in memory at once (one interval's events "
                    "are held together): check the frame times, lower the rate, or raise cmax.events.MAX_EVENTS "
                    "deliberately")
        return EventLimitError(
            f"the frame at {t_us} µs changes so much since the one at {self._t_us} µs that its interval may hold "
            f"up to {bound + round(noise):,} events over the {width}x{height} sensor, more than "
            f"cmax.events.MAX_EVENTS={limit:,} that fit in memory at once (one interval's events are held "
            "together): insert frames between the two (adaptive sampling: cmax simulate without --no-adaptive, "
            "cmax.sim.iter_upsample), raise the thresholds, or raise cmax.events.MAX_EVENTS deliberately")

    # -- public ---------------------------------------------------------------------------
    def step(self, frame: object, t_us: int) -> Events:
        """Feed one frame taken at ``t_us``; return the events since the previous frame.

        Parameters
        ----------
        frame : array_like, shape (H, W) or (H, W, 3)
            Grey values in [0, 255] (uint8 or float); colour is BGR.
        t_us : int
            Time of the frame in µs, larger than that of the previous frame.

        Returns
        -------
        Events
            Events with ``t_prev <= t <= t_us``, sorted by time; none for the
            first frame, which only initialises ``L_ref``.

        Raises
        ------
        cmax.events.EventLimitError
            When the interval's crossings could exceed ``cmax.events.MAX_EVENTS``
            (a 4K frame flashing to white at 35 thresholds a pixel), before
            anything is allocated; the simulator is left as it was.

        Warns
        -----
        UserWarning
            Once per simulator, when the first frame (after construction or
            :meth:`reset`) is float in [0, 1] with fractional values
            (:func:`unit_range_note`): most likely a [0, 1] image, simulated as
            given (nearly black to ESIM), not rescaled.
        """
        t_us = _whole("t_us", t_us)
        grey = _grey_frame(frame, "frame")
        if self._shape is None and not self._unit_warned:  # the first frame tells the scale of the stream
            note = unit_range_note(grey, "frames")
            if note is not None:
                self._unit_warned = True
                warnings.warn(note, UserWarning, stacklevel=2)
        if self._shape is not None:
            if grey.shape != self._shape:
                raise ValueError(f"frame has shape {grey.shape[:2]}, earlier frames {self._shape}")
            if t_us <= self._t_us:
                raise ValueError(f"t_us must increase: got {t_us} µs after {self._t_us} µs")
        return self._feed(_log_grey(grey, self.settings.log_eps, self._table), t_us)

    def _feed(self, log: np.ndarray, t_us: int) -> Events:
        if self._shape is None:
            self._initialize(log, t_us)
            return Events.empty(log.shape[1], log.shape[0])
        return self._advance(log, t_us)

    def simulate(self, frames: object, timestamps_us: object) -> Events:
        """Events of a whole sequence, from a fresh state.

        Parameters
        ----------
        frames : array_like, shape (T, H, W) or (T, H, W, 3)
            Grey values in [0, 255] (uint8 or float); colour is BGR.
        timestamps_us : array_like, shape (T,)
            Frame times in µs, integers, strictly increasing.

        Returns
        -------
        Events
            All events, sorted by time; width W, height H. Afterwards the
            simulator holds the state after the last frame, so :meth:`step`
            can go on.

        Warns
        -----
        UserWarning
            Float frames whose values all lie in [0, 1] (not all zero): most
            likely a [0, 1] image, which ESIM sees as nearly black; they are
            simulated as given, not rescaled.
        """
        frames = np.asarray(frames)
        if frames.ndim not in (3, 4) or (frames.ndim == 4 and frames.shape[3] != 3):
            raise ValueError(
                f"frames must have shape (T, H, W) or (T, H, W, 3), got {frames.shape}"
            )
        times = _timestamps(timestamps_us)
        if times.size != frames.shape[0]:
            raise ValueError(
                f"timestamps_us has {times.size} entries but frames has {frames.shape[0]} frames"
            )
        if frames.dtype.kind == "f" and frames.size and 0 < np.nanmax(frames) <= 1:
            warnings.warn(f"frames are floats in [{np.nanmin(frames):g}, {np.nanmax(frames):g}]: ESIM takes grey "
                          "values in [0, 255], so to it the whole sequence is nearly black (a [0, 1] image? "
                          "multiply it by 255)", UserWarning, stacklevel=2)
            self._unit_warned = True
        self.reset()
        eps = self.settings.log_eps
        sink = _Columns(0)
        for i, (frame, t_us) in enumerate(zip(frames, times)):
            log = _log_grey(_grey_frame(frame, f"frames[{i}]"), eps, self._table)
            if self._shape is None:
                self._initialize(log, int(t_us))
            else:
                self._advance(log, int(t_us), sink)
        if self._shape is None:
            raise ValueError("frames must hold at least one frame")
        height, width = self._shape
        return sink.events(width, height)


class _Columns:
    """x, y, t, p columns filled frame after frame; capacity doubles when it runs out."""

    def __init__(self, capacity: int) -> None:
        self.n = 0
        self.columns = (np.empty(capacity, np.uint16), np.empty(capacity, np.uint16),
                        np.empty(capacity, np.int64), np.empty(capacity, np.int8))

    def reserve(self, m: int) -> int:
        """Make room for ``m`` more events; returns where they start (and counts them)."""
        if self.n + m > self.columns[0].size:
            capacity = max(self.n + m, 2 * self.columns[0].size, 1 << 16)
            grown = tuple(np.empty(capacity, c.dtype) for c in self.columns)
            for old, new in zip(self.columns, grown):
                new[:self.n] = old[:self.n]
            self.columns = grown
        offset, self.n = self.n, self.n + m
        return offset

    def append(self, events: Events) -> None:
        offset = self.reserve(len(events))
        for column, name in zip(self.columns, "xytp"):
            column[offset:self.n] = getattr(events, name)

    def events(self, width: int, height: int) -> Events:
        """The columns filled so far (views), as Events."""
        return Events._trusted(*(c[:self.n] for c in self.columns), width, height)


def _timestamps(values: object) -> np.ndarray:
    times = np.asarray(values)
    if times.ndim != 1:
        raise ValueError(f"timestamps_us must be one-dimensional (T,), got shape {times.shape}")
    if times.dtype.kind == "b" or times.dtype.kind not in "iuf":
        raise TypeError(f"timestamps_us must hold integer microseconds, got dtype {times.dtype}")
    if times.dtype.kind == "f":
        if not np.isfinite(times).all() or not np.array_equal(times, np.round(times)):
            raise ValueError("timestamps_us must hold whole, finite numbers of microseconds")
    times = times.astype(np.int64)
    bad = np.flatnonzero(np.diff(times) <= 0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"timestamps_us must be strictly increasing; timestamps_us[{i + 1}]={times[i + 1]} µs "
            f"follows timestamps_us[{i}]={times[i]} µs"
        )
    return times
