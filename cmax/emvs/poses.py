"""Camera trajectories for EMVS: the accepted pose inputs and TUM trajectory files.

A trajectory is a pair ``(times_us (M,) int64, T_w_c (M, 4, 4) float64)`` of
strictly increasing times [µs] and camera-to-world poses. :func:`as_trajectory`
accepts that pair or any object with attributes ``times_us`` and ``poses``
(such as :class:`cmax.fitting.SequenceResult`, what :func:`cmax.fit_sequence`
returns). :func:`read_tum_trajectory` reads the TUM text format
``t tx ty tz qx qy qz qw`` (``t`` in seconds) that ``cmax fit`` writes
(``trajectory.txt``) and that the Event Camera Dataset ships as
``groundtruth.txt``. :func:`tum_header` gives the ``#`` lines ``cmax fit`` writes above its poses (the
frame, the units, and whether the translation is metric); :func:`trajectory_up_to_scale` reads them back.
"""
from __future__ import annotations

import os
import re
import warnings
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

__all__ = ["as_trajectory", "read_tum_trajectory", "check_coverage", "check_header", "tum_header",
           "trajectory_up_to_scale", "UP_TO_SCALE"]

#: Largest tolerated deviation of R^T R from the identity in a pose.
_ROTATION_TOLERANCE = 1e-4


def as_trajectory(poses: object, name: str = "poses") -> tuple[np.ndarray, np.ndarray]:
    """Validate a trajectory given as ``(times_us, T_w_c)`` or an object with ``times_us`` and ``poses``.

    Parameters
    ----------
    poses : tuple or object
        ``(times_us (M,), T_w_c (M, 4, 4))``, or anything with attributes
        ``times_us`` and ``poses`` of those shapes (e.g. ``cmax.fit_sequence``'s result), or
        ``poses_t_us`` and ``poses`` (a :class:`cmax.sim.SyntheticSequence`'s ground truth).
    name : str
        Name used in error messages.

    Returns
    -------
    times_us : ndarray, shape (M,), int64
        Strictly increasing times [µs].
    T_w_c : ndarray, shape (M, 4, 4), float64
        Camera-to-world poses (a fresh copy).

    Examples
    --------
    >>> import numpy as np
    >>> times, T = as_trajectory(([0, 10], np.stack([np.eye(4)] * 2)))
    >>> times.dtype.name, T.shape
    ('int64', (2, 4, 4))
    """
    if isinstance(poses, (tuple, list)):
        if len(poses) != 2:
            raise ValueError(f"{name} must be a pair (times_us (M,), T_w_c (M, 4, 4)), got {len(poses)} items")
        times, matrices = poses
    elif hasattr(poses, "times_us") and hasattr(poses, "poses"):
        times, matrices = poses.times_us, poses.poses
    elif hasattr(poses, "poses_t_us") and hasattr(poses, "poses"):      # a SyntheticSequence's ground truth
        times, matrices = poses.poses_t_us, poses.poses
    else:
        raise TypeError(
            f"{name} must be (times_us, T_w_c) or an object with attributes times_us (or poses_t_us) and poses "
            f"(e.g. cmax.fit_sequence's result, a cmax.sim.SyntheticSequence), got {type(poses).__name__}"
        )
    times = np.asarray(times)
    if times.ndim != 1 or times.size < 1:
        raise ValueError(f"{name}: times_us must have shape (M,) with M >= 1, got {times.shape}")
    if times.dtype.kind not in "iu":
        if times.dtype.kind != "f" or not np.all(np.isfinite(times)) or np.any(times != np.round(times)):
            raise ValueError(f"{name}: times_us must be whole microseconds (integers), got dtype {times.dtype}")
    times = times.astype(np.int64)
    if np.any(np.diff(times) <= 0):
        raise ValueError(f"{name}: times_us must be strictly increasing")
    matrices = np.array(matrices, dtype=np.float64)
    if matrices.shape != (times.size, 4, 4):
        raise ValueError(f"{name}: T_w_c must have shape ({times.size}, 4, 4), got {matrices.shape}")
    if not np.isfinite(matrices).all():
        raise ValueError(f"{name}: T_w_c must be finite")
    if not np.allclose(matrices[:, 3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name}: T_w_c must be homogeneous (last row 0 0 0 1)")
    R = matrices[:, :3, :3]
    error = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max()
    if error > _ROTATION_TOLERANCE or np.any(np.linalg.det(R) <= 0):
        raise ValueError(f"{name}: the rotation part of T_w_c must be a rotation matrix (|R^T R - I| = {error:.2g})")
    return times, matrices


#: Two consecutive poses more than this many times the events' span apart, with every event between them, are
#: refused by :func:`check_coverage`: a trajectory in another time unit, not a motion.
SPARSE_POSES_RATIO = 1000


def check_coverage(times_us: np.ndarray, t_first_us: int, t_last_us: int, name: str = "poses") -> None:
    """Raise ``ValueError`` unless ``[times_us[0], times_us[-1]]`` covers ``[t_first_us, t_last_us]``, and when
    every event lies between two consecutive poses more than :data:`SPARSE_POSES_RATIO` times the events' span
    apart (a trajectory whose times are in µs or ms read as seconds: the camera would barely move).

    >>> import numpy as np
    >>> check_coverage(np.array([0, 5_000_000_000]), 0, 300_000)
    Traceback (most recent call last):
    ...
    ValueError: every event (0.3 s) lies between two poses 5e+03 s apart, 1.7e+04 times the events' span: the camera cannot move over the events; are the poses' times in seconds (TUM: t[s]; times in µs read as seconds are 10^6 times too long)?
    """
    if times_us[0] > t_first_us or times_us[-1] < t_last_us:
        raise ValueError(
            f"{name} cover [{int(times_us[0])}, {int(times_us[-1])}] µs but the events span "
            f"[{int(t_first_us)}, {int(t_last_us)}] µs; give poses over the whole span "
            "(or cut the events to the poses' span)"
        )
    span = max(int(t_last_us) - int(t_first_us), 1)
    before = int(np.searchsorted(times_us, t_first_us, side="right")) - 1
    after = int(np.searchsorted(times_us, t_last_us, side="left"))
    if after - before == 1 and int(times_us[after]) - int(times_us[before]) > SPARSE_POSES_RATIO * span:
        gap = int(times_us[after]) - int(times_us[before])
        raise ValueError(
            f"every event ({span * 1e-6:.3g} s) lies between two {name} {gap * 1e-6:.2g} s apart, {gap / span:.2g} "
            "times the events' span: the camera cannot move over the events; are the poses' times in seconds (TUM: "
            "t[s]; times in µs read as seconds are 10^6 times too long)?"
        )


#: Largest time [s] a TUM file may state (about the year 5100 as seconds since 1970); larger ones are another unit
#: (nanoseconds since 1970: 1.7e18; microseconds: 1.7e15), refused by :func:`read_tum_trajectory`.
MAX_TUM_SECONDS = 10**11

_SMALLER_UNITS = (("nanoseconds", Decimal("1e-9")), ("microseconds", Decimal("1e-6")),
                  ("milliseconds", Decimal("1e-3")))


def _seconds_to_us(token: str, path: Path, line_number: int) -> int:
    try:
        seconds = Decimal(token)
    except InvalidOperation:
        raise ValueError(f"{path}:{line_number}: the time {token!r} is not a number") from None
    if not seconds.is_finite():
        raise ValueError(f"{path}:{line_number}: the time {token!r} is not a finite number of seconds")
    if abs(seconds) > MAX_TUM_SECONDS:
        unit = next((name for name, size in _SMALLER_UNITS if 10**8 <= abs(seconds) * size <= MAX_TUM_SECONDS), None)
        guess = ("another unit" if unit is None else
                 f"{unit} ({float(seconds * dict(_SMALLER_UNITS)[unit]):.6f} s since 1970 if so)")
        raise ValueError(f"{path}:{line_number}: the time {token} is too large for seconds (TUM's unit): these look "
                         f"like {guess}; write the times in seconds")
    return int((seconds * 1_000_000).to_integral_value())


#: A column name of a quaternion component in a header line: ``qw``, ``q_w``, ``q_RS_w`` (EuRoC), ``quat_w``.
_QUATERNION_COLUMN = re.compile(r"^q[a-z]*(?:_[a-z]+)*_?([wxyz])$", re.IGNORECASE)
#: A time unit other than seconds stated in a header line: ``timestamp [ns]`` (EuRoC), ``t[us]``, ``t [ms]``.
_OTHER_TIME_UNIT = re.compile(r"\b(?:t|time|times|timestamp|timestamps|stamp)\s*\[(ns|us|µs|ms)\]", re.IGNORECASE)


def check_header(line: str, path: str | os.PathLike) -> None:
    """Refuse a trajectory whose header comment states a layout other than TUM's ``t[s] tx ty tz qx qy qz qw``.

    ``line`` is a comment line before the first pose. When it names the quaternion's columns with ``w``
    before ``x`` (``# timestamp tx ty tz qw qx qy qz``, EuRoC's ``q_RS_w [], q_RS_x [] ...``), or gives the
    time in ns, µs or ms (``#timestamp [ns]``), the numbers would be read in another order or unit than the
    file says: ``ValueError`` naming the file. A comment that names no such column is ignored.

    >>> check_header("# timestamp tx ty tz qx qy qz qw", "ok.txt")
    >>> check_header("# t x y z qw qx qy qz", "wxyz.txt")
    Traceback (most recent call last):
    ...
    ValueError: wxyz.txt: its header '# t x y z qw qx qy qz' puts the quaternion's w first (qw qx qy qz; a TUM trajectory is read as 't tx ty tz qx qy qz qw', w last: reorder the columns to qx qy qz qw)
    """
    text = line.strip()
    problems = []
    if unit := _OTHER_TIME_UNIT.search(text):
        problems.append(f"gives times in {unit.group(1)} (a TUM trajectory has seconds: convert the time column)")
    tokens = [token.strip("[]#") for token in re.split(r"[\s,;]+", text)]
    order = [found.group(1).lower() for token in tokens if (found := _QUATERNION_COLUMN.match(token))]
    if "w" in order and "x" in order and order.index("w") < order.index("x"):
        problems.append("puts the quaternion's w first (qw qx qy qz; a TUM trajectory is read as "
                        "'t tx ty tz qx qy qz qw', w last: reorder the columns to qx qy qz qw)")
    if problems:
        raise ValueError(f"{path}: its header {text!r} " + " and ".join(problems))


def read_tum_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read the TUM trajectory file at ``path``: one pose per line, ``t tx ty tz qx qy qz qw``.

    ``t`` is in seconds (read as a decimal, so absolute times keep their
    microseconds), the translation in metres, the unit quaternion in
    ``x y z w`` order (as ``cmax fit`` writes it and as the Event Camera
    Dataset's ``groundtruth.txt``); the pose is camera-to-world. Blank lines
    and lines starting with ``#`` are skipped, but a header comment before the
    first pose that names another layout (the quaternion's ``w`` first, times in
    ns, µs or ms) is refused (:func:`check_header`): a quaternion order or a time
    unit is never guessed. A file without a header cannot say its order: ``qw qx
    qy qz`` columns there are read as ``qx qy qz qw``, with a ``UserWarning``
    when the first pose reads as ``(1, 0, 0, 0)``: a half turn about x, or the
    identity written ``w x y z`` (the usual first pose of a trajectory).

    Returns
    -------
    times_us : ndarray, shape (M,), int64
    T_w_c : ndarray, shape (M, 4, 4), float64
    """
    from scipy.spatial.transform import Rotation

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    try:
        text_lines = path.read_text("utf-8").splitlines()
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not a text file: expected a TUM trajectory, one pose "
                         "'t tx ty tz qx qy qz qw' per line") from None
    times, values = [], []
    for number, line in enumerate(text_lines, start=1):
        text = line.strip()
        if not text:
            continue
        if text.startswith("#"):
            if not times:                      # a header: it must not state another layout
                check_header(text, path)
            continue
        tokens = text.replace(",", " ").split()
        if len(tokens) != 8:
            raise ValueError(f"{path}:{number}: expected 't tx ty tz qx qy qz qw' (8 numbers), got {len(tokens)}")
        times.append(_seconds_to_us(tokens[0], path, number))
        try:
            values.append([float(v) for v in tokens[1:]])
        except ValueError:
            raise ValueError(f"{path}:{number}: expected numbers, got {text!r}") from None
    if not times:
        raise ValueError(f"{path}: no poses in the file")
    values = np.asarray(values)
    if not np.isfinite(values).all():
        raise ValueError(f"{path}: non-finite numbers in the trajectory")
    norms = np.linalg.norm(values[:, 3:], axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        bad = int(np.argmax(np.abs(norms - 1.0)))
        raise ValueError(f"{path}: quaternion of pose {bad} has norm {norms[bad]:.6f}, expected 1")
    if np.allclose(np.abs(values[0, 3:]), [1.0, 0.0, 0.0, 0.0], atol=1e-9):
        warnings.warn(f"{path}: the first pose's quaternion (qx qy qz qw) is ({values[0, 3]:g}, 0, 0, 0), a half turn "
                      "about x, read as given; it is the identity if the columns are qw qx qy qz: check the file's "
                      "order (TUM: qx qy qz qw)", UserWarning, stacklevel=2)
    T = np.tile(np.eye(4), (len(times), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(values[:, 3:] / norms[:, None]).as_matrix()
    T[:, :3, 3] = values[:, :3]
    return as_trajectory((np.asarray(times, dtype=np.int64), T), name=str(path))


#: The words of a trajectory file's ``#`` line that mark its translation as known only up to scale (``cmax fit``
#: without a speed); :func:`trajectory_up_to_scale` looks for them.
UP_TO_SCALE = "translation up to scale"


def tum_header(scale_known: bool) -> list[str]:
    """The ``#`` lines above the poses of a TUM trajectory that ``cmax fit`` writes: the columns, the frame
    (camera-to-world) and the unit of the translation, metres when ``scale_known``, else :data:`UP_TO_SCALE`
    (each window's speed taken as 1 m/s). TUM readers (evo, :func:`read_tum_trajectory`) skip ``#`` lines.

    >>> tum_header(True)
    ['# t[s] tx ty tz qx qy qz qw (TUM)', '# T_w_c (camera-to-world); translation in metres']
    """
    unit = ("translation in metres" if scale_known else
            f"{UP_TO_SCALE}: no speed was given, each window's speed is taken as 1 m/s, not metres")
    return ["# t[s] tx ty tz qx qy qz qw (TUM)", f"# T_w_c (camera-to-world); {unit}"]


def trajectory_up_to_scale(path: str | os.PathLike) -> bool:
    """True when a ``#`` line of the TUM trajectory file at ``path`` says its translation is up to scale
    (:data:`UP_TO_SCALE`, as :func:`tum_header` writes it without a speed)."""
    with open(path, encoding="utf-8", errors="replace") as file:
        return any(line.lstrip().startswith("#") and UP_TO_SCALE in line for line in file)
