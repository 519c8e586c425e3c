"""Gyroscope samples for ``cmax fit --gyro`` and :func:`cmax.fit_sequence` (``gyro=``).

Two sources: the IMU stream of an AEDAT4 file (DAVIS cameras store deg/s; converted
to rad/s here), or a text file of ``t wx wy wz`` lines (``t`` in seconds on the
events' clock, the angular velocity in rad/s in the camera's axes; ``#`` starts a
comment), the gyroscope counterpart of a TUM trajectory.

An IMU's axes are not the camera's: the DAVIS's x and z point the other way (the camera's x right,
y down, z forward; uzh-rpg/rpg_dvs_ros's DAVIS driver turns the IMU into the camera's frame as
``(-gx, gy, -gz)``). :data:`IMU_AXES` holds the known cameras' turn; for any other camera the axes must
be stated (``axes=``, ``cmax fit --gyro-axes``), never assumed.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from cmax.io._checks import check_time_unit, times_to_us
from cmax.io.aedat4 import aedat4_streams, read_aedat4_imu
from cmax.io.errors import FormatError

__all__ = ["IMU_AXES", "parse_axes", "read_gyro"]

#: The camera's axes in the IMU's, by the AEDAT4 stream's ``source`` (the camera's name up to its serial number):
#: ``"-x,y,-z"`` reads camera x = -IMU x, camera y = IMU y, camera z = -IMU z.
IMU_AXES = {"DAVIS": "-x,y,-z"}


def parse_axes(text: str) -> np.ndarray:
    """The signed permutation (3, 3) that turns IMU readings into the camera's axes, from ``"-x,y,-z"``: the
    camera's x, y and z, each as a signed IMU axis (``omega_camera = M @ omega_imu``).

    >>> import numpy as np
    >>> parse_axes("-x,y,-z").tolist()
    [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]
    >>> parse_axes("y,x,-z") @ np.array([1.0, 2.0, 3.0])
    array([ 2.,  1., -3.])
    """
    parts = [part.strip().lower() for part in str(text).split(",")]
    if len(parts) != 3 or any(not re.fullmatch(r"[+-]?[xyz]", part) for part in parts) \
            or sorted(part[-1] for part in parts) != ["x", "y", "z"]:
        raise ValueError(f"gyro axes must name each IMU axis once, signed, as the camera's x,y,z (e.g. '-x,y,-z' or "
                         f"'y,x,-z'), got {text!r}")
    matrix = np.zeros((3, 3))
    for row, part in enumerate(parts):
        matrix[row, "xyz".index(part[-1])] = -1.0 if part.startswith("-") else 1.0
    return matrix


def _known_axes(path: Path) -> str:
    """:data:`IMU_AXES` of the camera that wrote the first IMU stream of the AEDAT4 file ``path``."""
    sources = [stream.source for stream in aedat4_streams(path) if stream.type_identifier == "IMUS"]
    source = sources[0] if sources else ""
    for prefix, axes in IMU_AXES.items():
        if source.upper().startswith(prefix):
            return axes
    raise ValueError(f"{path}: the IMU of {source or 'an unnamed camera'!r} has no known orientation against the "
                     f"camera (known: {', '.join(IMU_AXES)}): state the camera's axes in the IMU's with axes= "
                     "(cmax fit --gyro-axes=...), e.g. '-x,y,-z' for a DAVIS")


#: The first bytes of every HDF5 file.
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _refuse_binary(path: Path) -> None:
    """FormatError naming what ``path`` is when it is an HDF5 file (not a gyro text file): an MVSEC data file's IMU
    (``davis/<camera>/imu``) is not read, its column order and its axes against the camera (the camchain's
    ``T_cam_imu``) being stated nowhere in the file; OSError when it cannot be read."""
    with open(path, "rb") as file:
        if file.read(len(HDF5_SIGNATURE)) != HDF5_SIGNATURE:
            return
    imus = []
    try:
        import h5py

        with h5py.File(path, "r") as file:
            davis = file.get("davis")
            imus = [f"davis/{name}/imu" for name in sorted(davis) if "imu" in davis[name]] \
                if isinstance(davis, h5py.Group) else []
    except (ImportError, OSError, KeyError, TypeError):
        pass                                       # the refusal below names an HDF5 file all the same
    what = (f"an MVSEC data file (IMU {', '.join(imus)}): its IMU is not read, since neither its column order nor "
            "its axes against the camera (the camchain's T_cam_imu) are stated in the file" if imus
            else "an HDF5 file, not a gyro file")
    raise FormatError(f"{path} is {what}; --gyro reads an AEDAT4 file's IMU (.aedat4) or text lines 't wx wy wz' "
                      "(s, rad/s, in the camera's axes: x right, y down, z forward): write those, or pass --omega "
                      "wx,wy,wz")


def read_gyro(path: str | os.PathLike, *, time_unit: str | None = None,
              axes: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gyroscope samples of ``path``: ``times_us`` (N,) int64 and ``omega`` (N, 3) float64 [rad/s] in the camera's
    axes (x right, y down, z forward).

    Text times are seconds unless ``time_unit`` states another unit, rounded to
    the nearest µs (half to even); AEDAT4 stores integer µs.

    ``axes``: the camera's axes in the IMU's (:func:`parse_axes`, e.g. ``"-x,y,-z"``). Default: for an AEDAT4
    file, :data:`IMU_AXES` of the camera that wrote it (a DAVIS: ``"-x,y,-z"``; another camera is refused
    without ``axes``); for a text file, ``"x,y,z"`` (its lines are in the camera's axes already).

    Raises
    ------
    FormatError
        A text file whose lines are not four numbers, or holding a non-finite
        time or angular velocity; a file that is not text (an HDF5 file, e.g. MVSEC's, whose IMU is not read).
    ValueError
        An AEDAT4 file without an IMU stream, or from a camera whose IMU axes are not known, without
        ``axes``; ``axes`` that are not a signed permutation.
    OSError
        The file cannot be read.
    """
    path = Path(path)
    unit = check_time_unit(time_unit) or "s"
    if path.suffix.lower() == ".aedat4":
        if time_unit not in (None, "us"):
            raise ValueError(f"{path}: AEDAT4 stores integer microseconds; time_unit={time_unit!r} does not apply")
        imu = read_aedat4_imu(path, sort=True)
        turn = parse_axes(axes if axes is not None else _known_axes(path))
        return imu.t.astype(np.int64), np.radians(imu.gyroscope.astype(np.float64)) @ turn.T
    _refuse_binary(path)
    try:
        table = np.loadtxt(path, comments="#", ndmin=2, dtype=np.float64)
    except UnicodeDecodeError:
        raise FormatError(f"{path} is not a text file (its bytes are not UTF-8): a gyro file is an AEDAT4 file's IMU "
                          "(.aedat4) or text lines 't wx wy wz' (s, rad/s, the camera's axes)") from None
    except ValueError as error:
        raise FormatError(f"{path}: gyro lines must be 't wx wy wz' (s, rad/s): {error}") from None
    if table.shape[1] != 4:
        raise FormatError(f"{path}: gyro lines must be 't wx wy wz' (s, rad/s), got {table.shape[1]} columns")
    if not np.isfinite(table[:, 1:]).all():
        row = int(np.flatnonzero(~np.isfinite(table[:, 1:]).all(axis=1))[0])
        raise FormatError(f"{path}: gyro sample {row} has a non-finite angular velocity {table[row, 1:].tolist()}")
    turn = parse_axes("x,y,z" if axes is None else axes)
    return times_to_us(table[:, 0], unit, f"{path}: gyro time"), table[:, 1:] @ turn.T
