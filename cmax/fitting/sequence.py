"""``cmax.fit_sequence``: fit a recording window by window and integrate the trajectory."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from tqdm.auto import tqdm

from cmax._threads import torch_threads_scope
from cmax.camera import camera_and_intrinsics, pinhole_events
from cmax.events import Events, check_time_us, uncovered_tail, window_starts
from cmax.fitting.api import MIN_WINDOW_EVENTS, FitResult, _check_inputs, _check_speed, _sensor_pixels, _settings, fit
from cmax._workers import recorded, reissue
from cmax.fitting.batch import FitTask, check_jobs, check_options, run_tasks
from cmax.fitting.quality import MotionScorer, Verdict, _distance_deg, choose_from_neighbours, choose_from_run
from cmax.fitting.settings import FitSettings
from cmax.fitting.window import Window
from cmax.geometry import se3_exp

__all__ = ["SequenceResult", "fit_sequence", "check_gyro", "window_gyro", "constant_gyro", "neighbour_consensus",
           "smooth_from_neighbours", "prior_neighbours"]


@dataclass(frozen=True, eq=False)
class SequenceResult:
    """Window-by-window fits and the integrated trajectory.

    Attributes
    ----------
    results : tuple of FitResult
    times_us : ndarray (M + 1,) int64
        Start [µs] of every fitted window, then the end of the last (M: ``len(results)``).
    poses : ndarray (M + 1, 4, 4) float64
        ``T_w_c`` (translation [m], or up to scale) at ``times_us``, the first the identity; between two starts the
        camera moves with the window's constant twist (metric only when every
        window's ``scale_known``).
    skipped_us : ndarray (S,) int64
        Start [µs] of every window not fitted (fewer than ``min_events`` events): over those the
        poses carry the last fitted window's twist (constant velocity; before the first fit they stand
        still), an assumption, not a measurement.
    uncovered_us : (2,) int tuple or None
        ``(start, end)`` [µs, end exclusive] of the recording after the last whole window, not fitted (shorter
        than a window; :func:`cmax.events.uncovered_tail`); None when the windows reach its last event.
    """

    results: tuple
    times_us: np.ndarray
    poses: np.ndarray
    skipped_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    uncovered_us: tuple[int, int] | None = None

    @property
    def verdicts(self) -> tuple:
        """Each fitted window's :class:`~cmax.fitting.quality.Verdict` (``results[i].verdict``)."""
        return tuple(r.verdict for r in self.results)

    def counts(self) -> dict[str, int]:
        """How many fitted windows have each verdict (``{"ok": n, "ambiguous": n, "low_parallax": n,
        "failed": n}``), and ``"resolved"``: the ambiguous ones resolved from their neighbours."""
        counts = {v.value: sum(r.verdict is v for r in self.results) for v in Verdict}
        counts["resolved"] = sum(r.quality is not None and r.quality.resolved for r in self.results)
        return counts


def check_gyro(gyro: object) -> tuple[np.ndarray, np.ndarray]:
    """Validated gyroscope samples: ``(times_us (N,) int64 increasing, omega (N, 3) float64 [rad/s])``, N >= 2."""
    try:
        times, omega = gyro
        times = np.asarray(times)
        omega = np.asarray(omega, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("gyro must be (times_us (N,), omega (N, 3) [rad/s])") from None
    if times.ndim != 1 or len(times) < 2 or omega.shape != (len(times), 3):
        raise ValueError(f"gyro must be (times_us (N,), omega (N, 3) [rad/s]) with N >= 2, got shapes "
                         f"{times.shape} and {omega.shape}")
    if not np.issubdtype(times.dtype, np.number) or not np.isfinite(times).all() or np.any(np.diff(times) <= 0):
        raise ValueError("gyro times_us must be finite and strictly increasing")
    if not np.isfinite(omega).all():
        raise ValueError("gyro omega must be finite")
    return times.astype(np.int64), omega


def constant_gyro(omega: object, t0_us: int, t1_us: int) -> tuple[np.ndarray, np.ndarray]:
    """Gyroscope samples (as :func:`check_gyro` returns them) that read the constant ``omega`` (3,) [rad/s]
    from ``t0_us`` to ``t1_us`` [µs]: a known rotation for every window of ``fit_sequence(gyro=)`` (e.g. zero
    for a linear stage).

    Examples
    --------
    >>> times, omega = constant_gyro([0.0, 0.1, 0.0], 0, 1000)
    >>> times.tolist(), omega.tolist()
    ([0, 1000], [[0.0, 0.1, 0.0], [0.0, 0.1, 0.0]])
    """
    return check_gyro((np.array([int(t0_us), int(t1_us)]), np.tile(np.asarray(omega, float), (2, 1))))


def window_gyro(gyro: tuple[np.ndarray, np.ndarray], t0_us: int, t1_us: int) -> np.ndarray:
    """Mean angular velocity (3,) [rad/s] over ``[t0_us, t1_us]`` of the samples of :func:`check_gyro`,
    linearly interpolated between them (the window's constant rotation of ``cmax.fit(..., omega=)``)."""
    times, omega = gyro
    _check_gyro_covers(gyro, t0_us, t1_us)
    inside = times[(times > t0_us) & (times < t1_us)]
    t = np.concatenate([[t0_us], inside, [t1_us]]).astype(np.float64)
    values = np.column_stack([np.interp(t, times, omega[:, axis]) for axis in range(3)])
    areas = 0.5 * (values[1:] + values[:-1]) * np.diff(t)[:, None]          # trapezoids (numpy 1.x has no trapezoid)
    return areas.sum(0) / (t[-1] - t[0])


def fit_sequence(source, K: object, model: str = "se3", *, window_us: int = 166_500, step_us: int | None = None,
                 speed: float | None = None, gyro: object = None, min_events: int = 1000,
                 jobs: int | None = 1, warm_start: bool | None = None, progress: bool = False,
                 store=None, **fit_options) -> SequenceResult:
    """Fit consecutive windows of a recording, warm-starting each from the previous (or all of them in
    parallel, cold); resolve the ambiguous windows from their neighbours; smooth the motion across windows.

    Parameters
    ----------
    source : Events or cmax.io.H5Reader
        Anything with ``window(t0_us, t1_us)`` (a reader) or an :class:`Events`.
    K : array_like (3, 3) or cmax.Camera
        Pinhole intrinsics [px] of the events; or the :class:`cmax.Camera` of their sensor, whose
        distortion (if any) each window's fit undoes as :func:`cmax.fit` does (sub-pixel positions for the
        warp, nearest undistorted pixels for the masks; a window's event count is that of its events that
        land inside the undistorted image).
    model : {"se3", "rotation", "flow"}
        The motion model of every window, as in :func:`cmax.fit`.
    window_us, step_us : int
        Window length and the step between window starts [µs] (``step_us`` defaults to ``window_us``).
        Only whole windows are fitted (:func:`cmax.events.window_starts`: those that end by the last event, or
        at most 1% of a window after it): the end of the recording after the last one
        (``SequenceResult.uncovered_us``) is not.
    speed : float, optional
        Known speed [m/s] of every window (se3; a ValueError with another model).
    gyro : (times_us (N,), omega (N, 3)), optional
        Gyroscope samples [µs, rad/s] in the camera's axes and on the events'
        clock (se3): each window's rotation is held at their mean over the
        window (:func:`window_gyro`, ``fit(..., omega=)``), and only the
        translation direction and the depth are fitted. A gyroscope's
        zero-rate offset goes straight into the depth: calibrate it first.
        The samples must span every window (checked before the first fit).
    min_events : int
        At least :data:`cmax.fitting.api.MIN_WINDOW_EVENTS` (10). Windows with fewer events are skipped
        (``SequenceResult.skipped_us``, with a warning): over them the trajectory carries the last fitted
        window's twist.
    jobs : int or None
        Worker processes of :func:`cmax.fitting.batch.fit_windows` (None: every available core). 1 (the
        default) fits in this process.
    warm_start : bool or None
        Start each window from the fit of the one before (``fit(..., init=previous)``). A warm start
        chains the windows, so it runs one window after another: ``jobs`` other than 1 needs
        ``warm_start=False`` (None, the default, picks True for ``jobs=1`` and False otherwise).
        Without warm starts every window is fitted on its own, in parallel over ``jobs`` workers,
        and the result equals ``fit_sequence(..., jobs=1, warm_start=False)`` bit for bit; the
        resolution of the ambiguous windows then runs after all of them, its re-fits in parallel
        too. What a warm start changes in accuracy and time on held-out windows: ``docs/fitting.md``.
    progress : bool
        A progress bar over the windows.
    store : object, optional
        Keeps each window's first fit as soon as it is done and gives back those of an earlier, interrupted run
        (``cmax fit``: :class:`cmax.io.window_store.WindowStore`). ``store.load(index, start_us)`` returns
        ``(result, caught)`` for the fitted window ``index`` whose window starts at ``start_us`` [µs] when it is
        already done (``caught``: its warnings, ``((category, message), ...)``, issued again), else None: that
        window is fitted. ``store.save(index, start_us, result, caught)`` is called with each new fit and returns
        the result to keep in memory in its place. The resolution of ambiguous windows and the smoothing run
        after all windows, on the kept results, as without a store; a warm start takes the loaded fit of the
        window before. Default None: nothing is kept outside memory.
    **fit_options
        Passed to :func:`fit`: ``settings=`` or fields of :class:`FitSettings` as keywords (not both),
        ``solver``, ``depth_grid``, ``num_threads``. ``pose``, ``omega`` and ``init`` are set per window
        here (a TypeError). The settings' ``quality`` (:class:`cmax.fitting.QualitySettings`, e.g.
        ``fit_sequence(..., quality=QualitySettings(...))``) rules the ambiguity test of every window
        and the resolution: once all windows are fitted, each ``ambiguous`` window takes, among the fit
        and its alternatives within noise, the motion closest to its ``ok`` neighbours' (up to
        ``quality.neighbours`` windows on each side;
        :func:`cmax.fitting.quality.choose_from_neighbours`); a run of ambiguous windows with no ``ok``
        window within reach takes the one motion its windows' own scores favour, summed over the run, when
        that beats every other by more than the pooled noise (:func:`cmax.fitting.quality.choose_from_run`);
        an alternative is re-fitted with its motion held (the depth swept for it).
        ``FitResult.quality.resolution`` says what was done, or why the window stays unresolved.

    Notes
    -----
    Consecutive windows share their motion. ``fit_sequence`` uses that three times: each window starts
    from the previous one's motion (``init=``), ambiguous windows are resolved from their confident
    neighbours, and, with ``quality.smoothing``, a motion prior across windows: a window whose data
    cannot tell its own motion from the consensus of its neighbours within ``quality.smoothing_span_s``
    on each side takes the consensus (:func:`smooth_from_neighbours`; ``FitResult.quality.resolution``
    says so and ``replaced`` keeps the window's own motion). A window whose motion is not steady
    (``quality.unsteady``: a start or a stop inside it, :func:`cmax.fitting.quality.rate_change`) takes
    the consensus without the test: its own fit is no evidence (without ``quality.smoothing`` it stays
    unresolved).

    Returns
    -------
    SequenceResult
        ``results`` (one :class:`FitResult` per fitted window, in time order), the integrated trajectory
        ``poses`` at ``times_us``, the windows skipped (``skipped_us``) and the end not covered
        (``uncovered_us``).

    Raises
    ------
    ValueError
        ``source`` holds no events; a bad ``K`` or ``speed`` (checked before any window, also when none is
        fitted), ``window_us``, ``step_us``, ``min_events``, ``jobs`` or ``gyro``.
    cmax.fitting.batch.WindowFitError
        ``jobs`` other than 1: a window's fit raised; ``index`` is its place among the fitted windows,
        the original exception is ``__cause__``. With ``jobs=1`` a window's exception propagates as it is.

    Warns
    -----
    Warning
        Each window's fit's warnings (e.g. :class:`~cmax.fitting.LowParallaxWarning`), in window order, each
        prefixed with ``window i:`` (``i``: its place among the fitted windows, as in ``results``), for any
        ``jobs``.
    UserWarning
        No window was fitted: the recording is shorter than one window, or no window holds ``min_events``
        events (the result then holds no window). Some windows were skipped: how many, and that the
        trajectory assumes a constant velocity across them.
    """
    settings, fit_options = _sequence_settings(fit_options)
    if speed is not None and model != "se3":
        raise ValueError(f"speed applies to model='se3', not {model!r}")
    jobs = check_jobs(jobs)
    warm_start = jobs == 1 if warm_start is None else warm_start
    if not isinstance(warm_start, (bool, np.bool_)):
        raise TypeError(f"warm_start must be True, False or None, got {warm_start!r}")
    if warm_start and jobs != 1:
        raise ValueError(f"warm starts chain the windows one after another: jobs={jobs} needs warm_start=False")
    if jobs != 1:                                # refused here rather than by every worker
        check_options(model, {"speed": speed, "settings": settings, **fit_options}, jobs)
    (camera, K), speed = camera_and_intrinsics(K), _check_speed(speed)
    if isinstance(min_events, (bool, np.bool_)) or not isinstance(min_events, (int, np.integer)) \
            or min_events < MIN_WINDOW_EVENTS:
        raise ValueError(f"min_events must be a whole number >= {MIN_WINDOW_EVENTS} (the fewest events a window can "
                         f"be fitted with), got {min_events!r}")
    window_us = check_time_us("window_us", window_us)
    step_us = window_us if step_us is None else check_time_us("step_us", step_us)
    if window_us <= 0 or step_us <= 0:
        raise ValueError(f"window_us and step_us must be positive, got {window_us}, {step_us}")
    if gyro is not None:
        if model != "se3":
            raise ValueError(f"gyro applies to model='se3', not {model!r}")
        gyro = check_gyro(gyro)
    if isinstance(source, Events):
        if len(source) == 0:
            raise ValueError("source holds no events: there is nothing to fit")
        t_start, t_end = int(source.t[0]), int(source.t[-1])
        take = lambda a, b: source.slice_time(a, b) if hasattr(source, "slice_time") else _slice(source, a, b)  # noqa: E731
    elif hasattr(source, "window"):
        t_start, t_end = int(source.t_start), int(source.t_end)
        take = source.window
    else:
        raise TypeError(f"source must be Events or a reader with window(t0_us, t1_us), got {type(source).__name__}")
    # each window's fit (also those the resolution runs again) undoes the lens itself, as cmax.fit does; the
    # windows' event counts and times are those of their undistorted events
    fit_K = K if camera is None else camera
    undistorted = (lambda events: events) if camera is None else (lambda events: pinhole_events(events, camera)[0])
    starts = window_starts(t_start, t_end, window_us, step_us)
    if gyro is not None and len(starts):
        _check_gyro_covers(gyro, t_start, starts[-1] + window_us - 1)
    steps, times = [], [t_start]                # steps: the index of the result each step moves with
    skipped: list[int] = []
    loaded: dict[int, tuple[FitResult, tuple]] = {}   # the windows the store already holds
    window_start: dict[int, int] = {}

    def tasks():                                 # taken one by one as the fits need them
        fitted = 0
        for t0 in starts.tolist():
            events = take(t0, t0 + window_us)
            counted = undistorted(events)
            if len(counted) >= min_events and counted.t[-1] > counted.t[0]:
                window_start[fitted] = t0
                if store is not None and (done := store.load(fitted, t0)) is not None:
                    loaded[fitted] = done
                else:
                    omega = None if gyro is None else window_gyro(gyro, int(counted.t[0]), int(counted.t[-1]))
                    yield FitTask(fitted, events, fit_K, model, dict(speed=speed, omega=omega, settings=settings,
                                                                      **fit_options))
                fitted += 1
            else:
                skipped.append(t0)
            steps.append(fitted - 1)
            times.append(t0 + step_us)

    caught_of: dict[int, tuple] = {}

    def kept(index: int, result: FitResult, caught: tuple) -> FitResult:
        caught_of[index] = caught
        return result if store is None else store.save(index, window_start[index], result, caught)

    if jobs == 1:
        fitted, first = {}, {}                   # first: each window's fit as it came, the warm start of the next
        for task in tqdm(tasks(), desc="windows", unit="window", total=len(starts), disable=not progress):
            previous = first.get(task.index - 1, loaded.get(task.index - 1, (None,))[0])
            start = previous if warm_start else None
            first[task.index], caught = recorded(lambda: fit(task.events, task.K, task.model, init=start,
                                                             **task.options))
            fitted[task.index] = (kept(task.index, first[task.index], caught), caught)
            first.pop(task.index - 1, None)      # only the window before is needed in full
    else:
        indices = []
        listed = (indices.append(task.index) or task for task in tasks())
        fitted = dict(zip(indices, run_tasks(listed, min(jobs, max(1, len(starts))), total=len(starts),
                                             progress=progress, on_result=kept)))
        fitted = {index: (result, caught_of[index]) for index, result in fitted.items()}
    done = {**loaded, **fitted}
    results = [done[index][0] for index in sorted(done)]
    for index in sorted(done):                   # in window order, each naming its window
        reissue(f"window {index}", done[index][1], stacklevel=2)
    if not results:
        why = (f"the recording ({(t_end - t_start + 1) * 1e-3:.1f} ms) is shorter than one window "
               f"({window_us * 1e-3:.1f} ms); pass a shorter window_us" if not len(starts) else
               f"none of its {len(starts)} window(s) holds min_events={min_events} events over more than one time "
               f"stamp; pass a longer window_us or a lower min_events (at least {MIN_WINDOW_EVENTS})")
        warnings.warn(f"fit_sequence: no window fitted: {why}", UserWarning, stacklevel=2)
    elif skipped:
        warnings.warn(f"fit_sequence: {len(skipped)} of {len(starts)} windows hold fewer than min_events={min_events} "
                      f"events over more than one time stamp and were not fitted (the first at "
                      f"{(skipped[0] - t_start) * 1e-6:.3f} s): across them the trajectory carries the last fitted "
                      "window's twist, a constant velocity that nothing measured (SequenceResult.skipped_us)",
                      UserWarning, stacklevel=2)
    results = _resolve_ambiguous(results, take, fit_K, speed, settings, fit_options, jobs)
    if settings.quality.smoothing and model == "se3":
        results = smooth_from_neighbours(results, take, fit_K, settings, fit_options, hold_omega=gyro is not None,
                                         neighbours=prior_neighbours(settings.quality, step_us))
    else:
        results = [_unresolved_unsteady(r, "the motion prior (QualitySettings.smoothing) is off")
                   if r.verdict is Verdict.AMBIGUOUS and r.quality.unsteady else r for r in results]
    poses = [np.eye(4)]
    for index in steps:
        twist = results[index].twist if index >= 0 else np.zeros(6)
        poses.append(poses[-1] @ se3_exp(twist * step_us * 1e-6))
    return SequenceResult(tuple(results), np.asarray(times, np.int64), np.stack(poses),
                          np.asarray(skipped, np.int64), uncovered_tail(t_start, t_end, window_us, step_us))


def _sequence_settings(fit_options: dict) -> tuple[FitSettings, dict]:
    """The one :class:`FitSettings` of every window of a sequence, from ``settings=`` or the keyword fields
    among ``fit_options`` (not both), and the other options of :func:`fit`."""
    taken = sorted({"pose", "omega", "init"} & set(fit_options))
    if taken:
        hint = ("; to hold the rotation of every window, give gyro= (a constant one: gyro=cmax.fitting.sequence."
                "constant_gyro(omega, first_us, last_us); cmax fit --omega)" if "omega" in taken else "")
        raise TypeError(f"fit_sequence() sets {taken} per window; it does not take them{hint}")
    fields = {k: v for k, v in fit_options.items() if k in FitSettings.__dataclass_fields__}
    rest = {k: v for k, v in fit_options.items() if k not in fields and k != "settings"}
    settings = fit_options.get("settings")
    if settings is not None and fields:
        raise TypeError(f"fit_sequence() takes settings= or keyword options, not both (got settings and "
                        f"{sorted(fields)})")
    if settings is not None and not isinstance(settings, FitSettings):
        raise TypeError(f"settings must be a FitSettings, got {type(settings).__name__}")
    return (settings if settings is not None else FitSettings(**fields)), rest


def _resolve_ambiguous(results: list[FitResult], take, K, speed: float | None, settings: FitSettings,
                       fit_options: dict, jobs: int = 1) -> list[FitResult]:
    """Each ambiguous se3 window resolved from its confident neighbours (:func:`choose_from_neighbours`),
    nearest first: the ``ok`` windows within ``QualitySettings.neighbours`` on each side, then, pass after
    pass, also the windows resolved in an earlier pass (with the motion they were resolved to), so that a run
    of ambiguous windows is resolved inwards from the confident windows at its ends rather than left
    unresolved; a window's outcome is fixed in the first pass that gives it a confident neighbour. A run with
    no confident window within reach is resolved, or left unresolved, by its pooled evidence
    (:func:`choose_from_run`). A chosen alternative is re-fitted with its motion held (``fit(..., pose=)``),
    its depth swept (the re-fits on ``jobs`` workers: each depends on the first fits alone)."""
    quality, out, refits = settings.quality, list(results), []
    confident = {i: (r.v, r.omega) for i, r in enumerate(results) if r.verdict is Verdict.OK}
    pending = [i for i, r in enumerate(results) if r.verdict is Verdict.AMBIGUOUS and not r.quality.unsteady]
    decisions: dict[int, tuple] = {}
    while pending:
        decided = {}
        for i in pending:
            near = [j for j in range(max(0, i - quality.neighbours), i + quality.neighbours + 1) if j in confident]
            if not near:
                continue
            r = results[i]
            chosen, resolved = choose_from_neighbours(r.v, r.omega, r.quality, [confident[j] for j in near],
                                                      (r.t1_us - r.t0_us) * 1e-6, quality.max_resolve_deg)
            through = sum(j in decisions for j in near)
            if through:
                resolved = replace(resolved, resolution=f"{resolved.resolution}; {through} of the neighbour(s) "
                                                        "resolved themselves from theirs")
            decided[i] = (chosen, resolved)
        if not decided:
            break
        for i, (chosen, resolved) in decided.items():
            decisions[i] = (chosen, resolved)
            if resolved.resolved:
                confident[i] = (results[i].v, results[i].omega) if chosen is None else (chosen.v, chosen.omega)
        pending = [i for i in pending if i not in decided]
    for run in _runs(pending):                   # no confident window anywhere near: the run's pooled evidence
        rs = [results[i] for i in run]
        chosen = choose_from_run([(r.v, r.omega) for r in rs], [r.quality for r in rs],
                                 [(r.t1_us - r.t0_us) * 1e-6 for r in rs], quality.max_resolve_deg)
        decisions.update(zip(run, chosen))
    for i, (chosen, resolved) in sorted(decisions.items()):
        r = results[i]
        if chosen is None:
            out[i] = replace(r, quality=resolved)
            continue
        refits.append((FitTask(i, take(r.t0_us, r.t1_us + 1), K, "se3",
                               dict(pose=np.r_[chosen.v, chosen.omega], settings=settings, **fit_options)), resolved))
    if jobs == 1 or len(refits) < 2:
        fitted = [fit(task.events, task.K, task.model, **task.options) for task, _ in refits]
    else:
        fitted = run_tasks([task for task, _ in refits], min(jobs, len(refits)))
    for (task, resolved), refit in zip(refits, fitted):
        r = results[task.index]
        out[task.index] = replace(refit, scale_known=speed is not None,
                                  quality=replace(resolved, replaced=(r.v, r.omega)),
                                  stages=r.stages + refit.stages, seconds=r.seconds + refit.seconds,
                                  iterations=r.iterations + refit.iterations,
                                  evaluations=r.evaluations + refit.evaluations)
    return out


def _runs(indices: list[int]) -> list[list[int]]:
    """``indices`` (ascending) split into runs of consecutive integers."""
    runs: list[list[int]] = []
    for i in indices:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs


def _around(results: list[FitResult], i: int, count: int) -> list[FitResult]:
    """Up to ``count`` windows on each side of ``results[i]``, not ``i`` itself."""
    return results[max(0, i - count):i] + results[i + 1:i + 1 + count]


def _confident(result: FitResult) -> bool:
    """A window whose motion its neighbours may lean on: ``ok``, or ambiguous and resolved, not unsteady."""
    q = result.quality
    return q is not None and not q.unsteady and (
        q.verdict is Verdict.OK or (q.verdict is Verdict.AMBIGUOUS and q.resolved))


def neighbour_consensus(results: list[FitResult], i: int, neighbours: int, min_count: int, *,
                        own_vote: bool = True) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The motion that window ``i`` and the confident windows around it agree on (a running median).

    The window itself and up to ``neighbours`` windows on each side that are ``ok`` or resolved: their unit
    translation directions' component-wise median, renormalised, and their angular velocities'
    component-wise median [rad/s]. The window votes too (unless ``own_vote`` is False: an unsteady window,
    whose fit is no evidence), so that one deviant neighbour among two does not move the consensus (a median
    filter over the sequence). Returns ``(direction (3,), omega (3,), count)`` with ``count`` the confident
    neighbours, or None with fewer than ``min_count`` of them (or directions that cancel out).
    """
    near = _around(results, i, neighbours)
    confident = [r for r in near if r.model == "se3" and _confident(r) and np.linalg.norm(r.v) > 0]
    if len(confident) < min_count or not np.linalg.norm(results[i].v) > 0:
        return None
    votes = [results[i], *confident] if own_vote else confident
    direction = np.median([r.v / np.linalg.norm(r.v) for r in votes], axis=0)
    if not np.linalg.norm(direction) > 1e-6:
        return None
    omega = np.median([r.omega for r in votes], axis=0)
    return direction / np.linalg.norm(direction), omega, len(confident)


def prior_neighbours(quality, step_us: int) -> int:
    """Windows on each side that the motion prior of :func:`fit_sequence` reads: as many steps of ``step_us``
    [µs] as fit into ``quality.smoothing_span_s``, at least ``quality.neighbours``.

    >>> from cmax.fitting import QualitySettings
    >>> prior_neighbours(QualitySettings(), 166_500), prior_neighbours(QualitySettings(), 1_000_000)
    (10, 2)
    """
    return max(quality.neighbours, int(round(quality.smoothing_span_s / (step_us * 1e-6))))


def smooth_from_neighbours(results: list[FitResult], take, K, settings: FitSettings, fit_options: dict, *,
                           hold_omega: bool = False, neighbours: int | None = None) -> list[FitResult]:
    """The motion prior across windows of :func:`fit_sequence` (``settings.quality.smoothing``).

    For every se3 window with a fitted direction, the running median of it and its confident neighbours
    within ``neighbours`` windows on each side (:func:`neighbour_consensus`; :func:`prior_neighbours` in
    :func:`fit_sequence`, ``quality.neighbours`` when None; with the window's own ``|v|``; its own omega
    with ``hold_omega``, a rotation given per window such as a gyroscope's)
    is scored against the window's fit on the fit's own patch-wise objective
    (:class:`cmax.fitting.quality.MotionScorer`: each motion with its own depth sweep, the gain against the
    patches' noise). When the gain is within noise, the window's data cannot tell its motion from its
    neighbours': it takes the consensus, re-fitted with the motion held (``fit(..., pose=)``, depth swept);
    otherwise it keeps its fit (the evidence beats the prior). The consensus comes from the windows as
    they were before this pass (one Jacobi step, so the order of the windows does not matter).
    An unsteady window (``Quality.unsteady``: its motion changes inside it, so its own fit is no evidence)
    takes the consensus of its neighbours without its own vote or the test, and counts as resolved.
    ``FitResult.quality.resolution`` says what was done; ``replaced`` holds the window's own motion.
    """
    quality, out = settings.quality, list(results)
    neighbours = quality.neighbours if neighbours is None else neighbours
    for i, r in enumerate(results):
        if r.model != "se3" or r.quality is None or r.verdict in (Verdict.FAILED, Verdict.LOW_PARALLAX):
            continue
        unsteady = r.quality.unsteady
        consensus = neighbour_consensus(results, i, neighbours, quality.min_consensus, own_vote=not unsteady)
        if consensus is None:
            if unsteady:
                out[i] = _unresolved_unsteady(r, f"fewer than min_consensus={quality.min_consensus} confident "
                                                 f"neighbour(s) within {neighbours} window(s)")
            continue
        direction, omega, count = consensus
        v_prior = np.linalg.norm(r.v) * direction
        omega_prior = r.omega if hold_omega else omega
        duration_s = (r.t1_us - r.t0_us) * 1e-6
        distance = _distance_deg(v_prior, omega_prior, r.v, r.omega, duration_s)
        head = f"smoothing: the consensus of {count} neighbour(s) is {distance:.1f} deg away"
        if distance < quality.smoothing_min_deg:
            if unsteady:
                out[i] = replace(r, quality=replace(r.quality, resolved=True, resolution=_join(
                    r.quality.resolution, f"{head}; kept the fit (the motion is not steady over the window: "
                                          "its neighbours' motion decides)")))
            continue
        events = take(r.t0_us, r.t1_us + 1)
        if unsteady:
            text = f"{head}; took it (the motion is not steady over the window: its own fit is no evidence)"
        else:
            prior = _score_prior(events, K, r, v_prior, omega_prior, settings, fit_options)
            if prior is None:
                continue
            if not prior.within_noise:
                text = (f"{head}; kept the fit (it scores better beyond noise: gain {prior.gain:.3g} > "
                        f"{prior.noise:.3g})")
                out[i] = replace(r, quality=replace(r.quality, resolution=_join(r.quality.resolution, text)))
                continue
            text = f"{head}; took it (within noise: gain {prior.gain:.3g} <= {prior.noise:.3g})"
        refit = fit(events, K, "se3", pose=np.r_[v_prior, omega_prior], settings=settings, **fit_options)
        q = replace(r.quality, resolution=_join(r.quality.resolution, text), resolved=r.quality.resolved or unsteady,
                    replaced=r.quality.replaced if r.quality.replaced is not None else (r.v, r.omega))
        out[i] = replace(refit, scale_known=r.scale_known, quality=q, stages=r.stages + refit.stages,
                         seconds=r.seconds + refit.seconds, iterations=r.iterations + refit.iterations,
                         evaluations=r.evaluations + refit.evaluations)
    return out


def _unresolved_unsteady(result: FitResult, why: str) -> FitResult:
    """``result``, an unsteady window, with the resolution that says why its neighbours did not give it a motion."""
    text = f"unresolved: the motion is not steady over the window and {why}"
    return replace(result, quality=replace(result.quality, resolution=_join(result.quality.resolution, text)))


def _score_prior(events: Events, K, result: FitResult, v: np.ndarray, omega: np.ndarray, settings: FitSettings,
                 fit_options: dict):
    """The prior motion ``(v, omega)`` scored as an alternative of ``result`` on the window's own objective
    (an :class:`~cmax.fitting.quality.Alternative`), or None when the window has too few patches."""
    settings = _settings(settings, {}, "se3")
    sensor = _sensor_pixels(events, K)                  # K a Camera with a lens: the events' sub-pixel positions
    events, K = pinhole_events(events, K)
    with torch_threads_scope(len(events), threads=fit_options.get("num_threads", 1)):
        w = Window.from_events(events, _check_inputs(events, K, "se3"), settings,
                               fit_options.get("depth_grid", (24, 32)), sensor)
        scorer = MotionScorer.build(w, result.v, result.omega, float(np.linalg.norm(result.v)), settings.quality)
        return None if scorer is None else scorer.score("neighbours", v, omega)


def _join(first: str, second: str) -> str:
    return f"{first}; {second}" if first else second


def _check_gyro_covers(gyro: tuple[np.ndarray, np.ndarray], first_us: int, last_us: int) -> None:
    """Raise when the gyroscope samples do not span ``[first_us, last_us]`` (the windows' events)."""
    times = gyro[0]
    if times[0] > first_us or times[-1] < last_us:
        raise ValueError(
            f"gyro covers {int(times[0])}-{int(times[-1])} us, but the windows span {first_us}-{last_us} us: "
            "cut the events to the gyro's span (Events.slice_time) or pass samples over the whole recording")


def _slice(events: Events, t0_us: int, t1_us: int) -> Events:
    i, j = np.searchsorted(events.t, [t0_us, t1_us])
    return events[int(i):int(j)]
