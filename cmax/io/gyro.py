"""Gyroscope samples for ``cmax fit --gyro`` and :func:`cmax.fit_sequence` (``gyro=``).

Two sources: the IMU stream of an AEDAT4 file (DAVIS cameras store deg/s; converted
to rad/s here), or a text file of ``t wx wy wz`` lines (``t`` in seconds on the
events' clock, the angular velocity in rad/s in the camera's axes; ``#`` starts a
comment), the gyroscope counterpart of a TUM trajectory.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cmax.io._checks import check_time_unit, times_to_us
from cmax.io.aedat4 import read_aedat4_imu
from cmax.io.errors import FormatError

__all__ = ["read_gyro"]


def read_gyro(path: str | os.PathLike, *, time_unit: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gyroscope samples of ``path``: ``times_us`` (N,) int64 and ``omega`` (N, 3) float64 [rad/s].

    Text times are seconds unless ``time_unit`` states another unit, rounded to
    the nearest µs (half to even); AEDAT4 stores integer µs.

    Raises
    ------
    FormatError
        A text file whose lines are not four numbers, or holding a non-finite
        time or angular velocity.
    ValueError
        An AEDAT4 file without an IMU stream.
    OSError
        The file cannot be read.
    """
    path = Path(path)
    unit = check_time_unit(time_unit) or "s"
    if path.suffix.lower() == ".aedat4":
        if time_unit not in (None, "us"):
            raise ValueError(f"{path}: AEDAT4 stores integer microseconds; time_unit={time_unit!r} does not apply")
        imu = read_aedat4_imu(path, sort=True)
        return imu.t.astype(np.int64), np.radians(imu.gyroscope.astype(np.float64))
    try:
        table = np.loadtxt(path, comments="#", ndmin=2, dtype=np.float64)
    except ValueError as error:
        raise FormatError(f"{path}: gyro lines must be 't wx wy wz' (s, rad/s): {error}") from None
    if table.shape[1] != 4:
        raise FormatError(f"{path}: gyro lines must be 't wx wy wz' (s, rad/s), got {table.shape[1]} columns")
    if not np.isfinite(table[:, 1:]).all():
        row = int(np.flatnonzero(~np.isfinite(table[:, 1:]).all(axis=1))[0])
        raise FormatError(f"{path}: gyro sample {row} has a non-finite angular velocity {table[row, 1:].tolist()}")
    return times_to_us(table[:, 0], unit, f"{path}: gyro time"), table[:, 1:]
