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

from cmax.io.aedat4 import read_aedat4_imu
from cmax.io.errors import FormatError

__all__ = ["read_gyro"]


def read_gyro(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Gyroscope samples of ``path``: ``times_us`` (N,) int64 and ``omega`` (N, 3) float64 [rad/s].

    Raises
    ------
    FormatError
        A text file whose lines are not four numbers.
    ValueError
        An AEDAT4 file without an IMU stream.
    OSError
        The file cannot be read.
    """
    path = Path(path)
    if path.suffix.lower() == ".aedat4":
        imu = read_aedat4_imu(path, sort=True)
        return imu.t.astype(np.int64), np.radians(imu.gyroscope.astype(np.float64))
    try:
        table = np.loadtxt(path, comments="#", ndmin=2, dtype=np.float64)
    except ValueError as error:
        raise FormatError(f"{path}: gyro lines must be 't wx wy wz' (s, rad/s): {error}") from None
    if table.shape[1] != 4:
        raise FormatError(f"{path}: gyro lines must be 't wx wy wz' (s, rad/s), got {table.shape[1]} columns")
    return np.round(table[:, 0] * 1e6).astype(np.int64), table[:, 1:]
