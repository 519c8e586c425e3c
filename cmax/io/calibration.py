"""Calibration files -> :class:`Calibration`: the camera a calibration file states, and the :class:`cmax.Camera` it
describes (:meth:`Calibration.camera`).

:func:`read_calibration` reads ECD's ``calib.txt``, DSEC's ``cam_to_cam.yaml``, a Kalibr camchain (radtan or
equidistant, with its ``rectification_matrix`` / ``projection_matrix``), a ROS ``camera_info`` YAML (also as
``rostopic echo`` prints one) and OpenCV FileStorage YAML, without a YAML library (:func:`_yaml_tree`).
:func:`topic_side` tells which camera of a stereo rig a camchain camera is. The command line's ``--calib`` is this
reader (:mod:`cmax.cli.recording`).
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from cmax.camera import Camera, check_intrinsics, check_rotation, intrinsics_matrix

__all__ = ["Calibration", "read_calibration", "topic_side", "ROS_RADTAN_MODELS"]

#: The file DSEC ships beside its raw events (``events/left/rectify_map.h5``): the rectified pixel of each raw one.
DSEC_RECTIFY_MAP = "rectify_map.h5"


class Calibration(NamedTuple):
    """A camera as a calibration file (or ``--K`` / ``--distortion``) states it; :func:`read_calibration`.

    ``K`` (3, 3) [px] of the lens (None: not given, the file's ``gt/K`` is used); ``distortion``: its
    coefficients (radtan (4,) or (5,), (8,) of ROS's rational_polynomial, equidistant (4,)) or None; ``size``:
    ``(width, height)`` [px] the file states, or None; ``model``: ``"radtan"`` or ``"equidistant"``; ``rectification`` (3, 3) and ``rectified_K``
    (3, 3) [px]: a stereo rectification the file gives (Kalibr's ``rectification_matrix``, the left 3x3 of its
    ``projection_matrix``), into whose frame the events are undistorted, or None; ``topic``: the camera's
    ``rostopic`` in a Kalibr camchain (``/davis/left/image_raw``: which camera of a rig it is), or None;
    ``rectified_from``: where a DSEC ``cam_to_cam.yaml`` gave the rectification (``"extrinsics/R_rect0 and
    intrinsics/camRect0"``), None for a camchain's ``rectification_matrix`` / ``projection_matrix`` or none.
    """

    K: np.ndarray | None
    distortion: np.ndarray | None
    size: tuple[int, int] | None
    model: str = "radtan"
    rectification: np.ndarray | None = None
    rectified_K: np.ndarray | None = None
    topic: str | None = None
    rectified_from: str | None = None

    @property
    def pinhole_K(self) -> np.ndarray | None:
        """(3, 3) [px]: the K of the pixels the events are undistorted to, the one to fit with: ``rectified_K``
        or ``K``."""
        return self.K if self.rectified_K is None else self.rectified_K

    @property
    def undistorts(self) -> bool:
        """Whether the events must be mapped before a pinhole fit (a distortion, a rectification)."""
        return self.distortion is not None or self.rectification is not None or self.rectified_K is not None

    def camera(self, width: int, height: int, K: np.ndarray | None = None) -> Camera:
        """The :class:`cmax.Camera` this calibration describes, of a ``width`` x ``height`` [px] sensor: its ``K``
        (3, 3) [px], ``distortion`` of ``model``, ``rectification`` (3, 3) and ``rectified_K`` (3, 3) [px]
        (:attr:`cmax.Camera.pinhole_K`: the K of the pixels its ``undistort_events`` maps the events to).
        ``K`` (3, 3) [px] replaces the calibration's (needed when it gives none: a file's ``gt/K``).
        """
        return Camera(self.K if K is None else K, width, height, self.distortion, self.model, self.rectification,
                      self.rectified_K)


def topic_side(topic: str | None) -> str | None:
    """``'left'`` or ``'right'`` when a camchain camera's ``rostopic``, ``topic``, names that camera of a stereo rig
    (a path component ``left`` / ``right``, as MVSEC's ``/davis/left/image_raw``), else None.

    >>> topic_side("/davis/right/image_raw"), topic_side("/cam0/image_raw"), topic_side(None)
    ('right', None, None)
    """
    parts = set((topic or "").strip().strip("'\"").lower().split("/"))
    sides = [side for side in ("left", "right") if side in parts]
    return sides[0] if len(sides) == 1 else None


def _numbers(text: str) -> list[float]:
    return [float(v) for v in text.replace("[", " ").replace("]", " ").replace(",", " ").split()]


def read_calibration(path: str | Path, camera: str = "cam0") -> Calibration:
    """The :class:`Calibration` of ``camera`` in the calibration file ``path``: ``(K (3, 3) [px], distortion or
    None, (width, height) [px] or None, model, rectification (3, 3) or None, rectified_K (3, 3) [px] or None)``
    (a named tuple: ``K, distortion, size = read_calibration(path)[:3]``).

    * ECD ``calib.txt``: one line ``fx fy cx cy k1 k2 p1 p2 k3`` (or only ``fx fy cx cy``), one camera (a
      ``camera`` other than ``"cam0"`` is refused: it was read as this one without a word);
    * DSEC ``cam_to_cam.yaml``: ``intrinsics/<camera>`` with ``camera_matrix: [fx, fy, cx, cy]``,
      optional ``distortion_coeffs: [k1, k2, p1, p2]`` (radtan) and ``resolution: [w, h]``; a raw camera ``camN``
      (DSEC's events are raw) with ``extrinsics/R_rectN`` and ``intrinsics/camRectN`` beside it is rectified into
      camRectN's frame, that of DSEC's disparity maps (``rectification`` = ``R_rectN``, ``rectified_K`` =
      camRectN's K); ``camRectN`` itself is a pinhole without distortion, for events already rectified;
    * a ROS ``camera_info`` YAML (``camera_calibration``'s, ``rpg_dvs_ros``'s): ``camera_matrix``,
      ``distortion_model``, ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix`` as
      ``data: [...]``, ``image_width`` / ``image_height``; one camera; ``plumb_bob`` or ``rational_polynomial``
      with 4, 5 or 8 coefficients (an empty ``D``: none), ``equidistant`` with 4; also a CameraInfo message as
      ``rostopic echo`` / ``ros2 topic echo`` print it (``K``, ``D``, ``R``, ``P``, ``width``, ``height``);
    * a Kalibr camchain (``camchain.yaml``, as MVSEC and many DAVIS rigs ship): ``<camera>`` with
      ``intrinsics: [fx, fy, cx, cy]`` and the same keys; a pinhole camera with ``distortion_model: radtan``
      (``plumb_bob``; 4 or 5 coefficients) or ``equidistant`` (Kannala-Brandt fisheye, exactly 4: ``k1 k2 k3
      k4``). MVSEC's camchains also give each camera a ``rectification_matrix`` (3x3 ``R_rect``) and a
      ``projection_matrix`` (3x4 ``P_rect``): read as ``rectification`` and ``rectified_K`` (``P_rect``'s left
      3x3; its last column, a stereo baseline, does not move a camera's own rays), the frame of MVSEC's
      ``depth_image_rect``, into which ``--calib`` undistorts the events (:class:`cmax.Camera`). A rectification
      that moves nothing (``R = I``, ``P``'s K equal to K: a monocular camera's) is dropped.

    Lists may be written ``[a, b]`` or as ``- a`` lines (YAML's block style). A ``#`` comment at a line's end and a
    byte order mark at the file's start (what Windows editors save) are ignored, in every format. Quoted keys and
    values are read as YAML reads them (escapes decoded); what this reader does not read (anchors, aliases, merge
    keys, flow mappings ``{...}``, block scalars, tabs in the indentation, a second document) is refused naming
    the file and line, not misread.

    Raises FileNotFoundError, or ValueError naming the file and what is missing.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no calibration file at {path}")
    _check_not_binary(path)
    text = path.read_text("utf-8-sig", errors="replace")     # a byte order mark (Windows editors) is not text
    if path.suffix.lower() in (".yaml", ".yml"):
        values = _yaml_intrinsics(path, text, camera)
        try:
            fx, fy, cx, cy = _numbers(values["camera_matrix"])
            distortion = _numbers(values["distortion_coeffs"]) if "distortion_coeffs" in values else None
            size = tuple(int(v) for v in _numbers(values["resolution"])) if "resolution" in values else None
        except (KeyError, ValueError, TypeError):
            raise ValueError(f"{path}: intrinsics/{camera} needs camera_matrix: [fx, fy, cx, cy] (and optionally "
                             "distortion_coeffs, resolution: [w, h])") from None
        model = values.get("distortion_model", "radtan").strip()
        model = "radtan" if model == "plumb_bob" else model
        if model not in ("radtan", "equidistant"):
            raise ValueError(f"{path}: distortion_model {model!r} of {camera} is not supported (radtan / plumb_bob, "
                             "equidistant)")
        if size is not None and len(size) != 2:
            raise ValueError(f"{path}: resolution must be [width, height]")
        rectification = _yaml_matrix(path, camera, values, "rectification_matrix", (9,))
        projection = _yaml_matrix(path, camera, values, "projection_matrix", (12, 9))
        if model == "equidistant":
            if distortion is None or len(distortion) != 4 or not np.isfinite(distortion).all():
                raise ValueError(f"{path}: the equidistant (fisheye) distortion of {camera} must be 4 finite numbers "
                                 f"distortion_coeffs: [k1, k2, k3, k4], got {distortion}")
            K = intrinsics_matrix([fx, fy, cx, cy], f"{path}: {camera} intrinsics")
            return _no_rectification(Calibration(K, np.asarray(distortion, float), size, model, *_rectification(
                path, camera, rectification, projection), values.get("rostopic"), values.get("rectified_from")))
    else:
        lines = [line for line in (raw.split("#", 1)[0] for raw in text.splitlines()) if line.strip()]
        try:
            numbers = _numbers(lines[0]) if len(lines) == 1 else []
        except ValueError:
            numbers = []
        if len(numbers) not in (4, 8, 9):
            raise ValueError(f"{path}: expected one line 'fx fy cx cy [k1 k2 p1 p2 [k3]]' (ECD calib.txt)")
        if camera != "cam0":     # one camera: another name was read as this one without a word
            raise ValueError(f"{path} calibrates one camera (ECD calib.txt): camera {camera!r} (--calib-camera) "
                             "chooses one of a DSEC cam_to_cam.yaml or a Kalibr camchain .yaml; leave it out")
        (fx, fy, cx, cy), distortion, size = numbers[:4], numbers[4:] or None, None
        rectification = projection = values = None
    rational = values is not None and values.get("distortion_model_ros") in ROS_RADTAN_MODELS
    if distortion is not None and rational and not distortion:     # ROS's D: [] of a camera without distortion
        distortion = None
    if distortion is not None and (len(distortion) not in ((4, 5, 8) if rational else (4, 5))
                                   or not np.isfinite(distortion).all()):
        raise ValueError(f"{path}: the distortion must be 4 or 5 finite numbers (k1 k2 p1 p2 [k3])" + (
            f", or 8 (k1 k2 p1 p2 k3 k4 k5 k6: ROS's rational_polynomial); got {len(distortion)}" if rational else ""))
    K = intrinsics_matrix([fx, fy, cx, cy])
    return _no_rectification(Calibration(K, None if distortion is None else np.asarray(distortion, float), size,
                                         "radtan", *_rectification(path, camera, rectification, projection),
                                         None if values is None else values.get("rostopic"),
                                         None if values is None else values.get("rectified_from")))


#: The formats :func:`read_calibration` reads, as a refusal names them.
CALIBRATION_FORMATS = ("ECD calib.txt, DSEC cam_to_cam.yaml, a Kalibr camchain .yaml, a ROS camera_info .yaml or "
                       "OpenCV FileStorage .yaml")


def _check_not_binary(path: Path) -> None:
    """Refuse a binary file given as a calibration file (its bytes were parsed as text and refused as a malformed
    ``calib.txt``): ValueError naming ``path``, what it is and the file to give instead. DSEC's
    :data:`DSEC_RECTIFY_MAP` (an HDF5 table of rectified pixel positions, ``SEQ/events/left/``) names the
    sequence's ``SEQ/calibration/cam_to_cam.yaml``, which holds the same undistortion and rectification.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as folder:
    ...     table = Path(folder) / "rectify_map.h5"
    ...     _ = table.write_bytes(b"\\x89HDF\\r\\n\\x1a\\n" + bytes(8))
    ...     try:
    ...         _check_not_binary(table)
    ...     except ValueError as error:
    ...         print(str(error)[len(str(table)):].split(":")[0])
     is DSEC's rectify map (an HDF5 table of rectified pixel positions), not a calibration file
    """
    with open(path, "rb") as file:
        head = file.read(4096)
    if head.startswith(b"\x89HDF\r\n\x1a\n") and path.name == DSEC_RECTIFY_MAP:
        yaml = path.resolve().parent.parent.parent / "calibration" / "cam_to_cam.yaml"
        where = f" ({yaml})" if yaml.is_file() else " (SEQ/calibration/cam_to_cam.yaml of the sequence)"
        raise ValueError(f"{path} is DSEC's rectify map (an HDF5 table of rectified pixel positions), not a "
                         f"calibration file: pass the sequence's cam_to_cam.yaml{where}, which holds the same "
                         "undistortion and rectification (cam0 into camRect0's frame)")
    if head.startswith(b"\x89HDF\r\n\x1a\n") or b"\x00" in head:
        what = "an HDF5 file" if head.startswith(b"\x89HDF") else "a binary file"
        raise ValueError(f"{path} is {what}, not a calibration file: expected {CALIBRATION_FORMATS} (text)")


def _yaml_matrix(path: Path, camera: str, values: dict[str, str], key: str,
                 sizes: tuple[int, ...]) -> np.ndarray | None:
    """The numbers of ``values[key]`` (a matrix written as nested lists, flow or block style), or None when the
    camera has no such key; ValueError naming the file, camera and key when they are not ``sizes`` numbers."""
    if key not in values:
        return None
    try:
        numbers = [v for v in values[key].replace("[", " ").replace("]", " ").replace(",", " ").split() if v != "-"]
        matrix = np.array([float(v) for v in numbers])
    except ValueError:
        matrix = np.zeros(0)
    if matrix.size not in sizes or not np.isfinite(matrix).all():
        shapes = " or ".join({9: "3x3", 12: "3x4"}[n] for n in sizes)
        name = values.get(f"{key}_name", f"{camera}'s {key}")
        raise ValueError(f"{path}: {name} must be a {shapes} matrix of finite numbers, got {values[key]!r}")
    return matrix


def _rectification(path: Path, camera: str, rectification: np.ndarray | None,
                   projection: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(R (3, 3), rectified K (3, 3) [px])`` of a camera's ``rectification_matrix`` (9 numbers) and
    ``projection_matrix`` (12: 3x4, or 9), None where not given; ValueError naming the file when R is not a
    rotation or P's left 3x3 not a pinhole matrix."""
    R = K = None
    try:
        if rectification is not None:
            R = check_rotation(rectification.reshape(3, 3), f"{path}: {camera}'s rectification_matrix")
        if projection is not None:
            P = projection.reshape(3, -1)
            K = check_intrinsics(P[:, :3], f"{path}: {camera}'s projection_matrix (its left 3x3)")
    except TypeError as error:
        raise ValueError(str(error)) from None
    return R, K


def _no_rectification(calibration: Calibration) -> Calibration:
    """``calibration`` without a rectification that moves nothing: an identity ``R`` and a ``rectified_K`` equal
    to ``K`` (a monocular ROS camera_info's usual ``R = I``, ``P = [K | 0]``) are dropped."""
    R, K_rect = calibration.rectification, calibration.rectified_K
    if R is not None and np.array_equal(R, np.eye(3)):
        R = None
    if K_rect is not None and calibration.K is not None and np.array_equal(K_rect, calibration.K):
        K_rect = None
    return calibration._replace(rectification=R, rectified_K=K_rect,
                                rectified_from=None if R is None and K_rect is None else calibration.rectified_from)


def _yaml_tree(text: str) -> dict:
    """The nested mappings of a small YAML file as dicts of strings (no YAML library): ``key: value`` lines by
    their indentation; a key without a value opens a mapping, or a list when ``- item`` lines follow it (block
    style, as PyYAML writes by default), held as the list of its items' text (a flow list ``[a, b]`` stays one
    string, also when it goes on over several lines: :func:`_yaml_lines`); quoted keys and scalars as YAML reads
    them (:func:`_scalar`); a key whose value is a tag (OpenCV FileStorage's ``camera_matrix: !!opencv-matrix``)
    opens a mapping; :func:`_yaml_intrinsics` writes a block list back as ``[a, b, ...]``.

    What this reader does not read is refused (ValueError naming the line) rather than misread: anchors, aliases
    and merge keys (``&a``, ``*a``, ``<<``), flow mappings ``{...}``, block scalars (``|``, ``>``), a quoted value
    going on over lines, a line that is neither ``key: value`` nor ``- item``, a key given twice in one mapping,
    and what :func:`_yaml_lines` refuses (tabs in the indentation, several documents)."""
    root: dict = {}
    stack: list[tuple[int, dict]] = [(-1, root)]      # (indentation of the key that opened it, mapping)
    opened: tuple[dict, str, int] | None = None       # the last key without a value: (its mapping, key, indentation)
    for number, line in _yaml_lines(text):
        indent = len(line) - len(line.lstrip())
        item = line.strip()
        if item.startswith("-"):
            if opened is not None and indent >= opened[2]:
                parent, key, _ = opened
                if isinstance(parent[key], dict) and not parent[key]:
                    stack = [entry for entry in stack if entry[1] is not parent[key]]
                    parent[key] = []
                if isinstance(parent[key], list):
                    parent[key].append(_scalar(item[1:].strip(), number))
            continue
        while stack[-1][0] >= indent:
            stack.pop()
        key, value = _key_value(item, number)
        mapping = stack[-1][1]
        if key in mapping:
            raise ValueError(f"line {number}: the key {key!r} is given a second time in the same mapping (which one "
                             "holds? YAML readers differ: keep one)")
        if value and not (value.startswith("!") and len(value.split()) == 1):   # a tag alone: a mapping follows
            mapping[key] = _scalar(value, number)          # '' too is a value (an empty one)
            opened = None
        else:
            mapping[key] = {}
            stack.append((indent, mapping[key]))
            opened = (mapping, key, indent)
    return root


def _key_value(item: str, number: int) -> tuple[str, str]:
    """``(key, value text)`` of the YAML line ``item`` (stripped, without comment) on line ``number``: the key plain
    or quoted (read by :func:`_scalar`); ValueError for a line without ``key:`` and for a merge key ``<<``."""
    if item[:1] == "{":
        _scalar(item, number)                           # a flow mapping: refused, named
    if item[:1] in "\"'":
        end = _closing_quote(item)
        rest = item[end + 1:].lstrip() if end is not None else ""
        if not rest.startswith(":"):
            raise ValueError(f"line {number}: {_shown(item)} is neither 'key: value' nor '- item' (a quoted value that "
                             "goes on over lines is not read: write it on one line)")
        key, value = _scalar(item[:end + 1], number), rest[1:].strip()
    else:
        key, colon, value = item.partition(":")
        if not colon:
            raise ValueError(f"line {number}: {_shown(item)} is neither 'key: value' nor '- item' (a value that "
                             "goes on over lines is not read: write it on one line)")
        key, value = key.strip(), value.strip()
    if key == "<<":
        raise ValueError(f"line {number}: merge keys ('<<: *{value.lstrip('*')}') are not read: write the "
                         "camera's values out in full")
    return key, value


def _shown(text: str) -> str:
    """``text`` quoted for a message, cut to its first 40 characters."""
    return repr(text if len(text) <= 40 else text[:37] + "...")


def _closing_quote(text: str) -> int | None:
    """Index of the quote that closes the quoted scalar at the start of ``text`` (``"`` with ``\\`` escapes, or
    ``'`` with ``''`` for a quote), None when the line ends inside it."""
    quote, i = text[0], 1
    while i < len(text):
        if quote == '"' and text[i] == "\\":
            i += 2
            continue
        if text[i] == quote:
            if quote == "'" and text[i + 1:i + 2] == "'":
                i += 2
                continue
            return i
        i += 1
    return None


#: YAML's escapes of a double-quoted scalar (YAML 1.2, 5.7) other than ``\\x``, ``\\u`` and ``\\U``.
_ESCAPES = {"0": "\0", "a": "\a", "b": "\b", "t": "\t", "\t": "\t", "n": "\n", "v": "\v", "f": "\f", "r": "\r",
            "e": "\x1b", " ": " ", '"': '"', "/": "/", "\\": "\\", "N": "\x85", "_": "\xa0", "L": "\u2028",
            "P": "\u2029"}
#: Hex digits of YAML's ``\\x``, ``\\u`` and ``\\U`` escapes.
_HEX_ESCAPES = {"x": 2, "u": 4, "U": 8}


def _scalar(value: str, number: int) -> str:
    r"""The YAML scalar ``value`` (stripped, without comment) on line ``number`` as YAML reads it: a double-quoted
    one with its escapes decoded (``"\x6c"`` is ``l``), a single-quoted one with ``''`` as ``'``, a plain one as
    it is (a flow list ``[...]`` stays text). ValueError naming the line for what is not read rather than
    misread: an anchor or alias (``&a``, ``*a``), a flow mapping ``{...}``, a block scalar (``|``, ``>``), a tag
    before a value (``!!str x``), a quoted value that goes on over lines, an unknown escape.

    >>> _scalar('"/davis/\\x6ceft"', 1), _scalar("'it''s'", 1), _scalar("[1, 2]", 1)
    ('/davis/left', "it's", '[1, 2]')
    """
    first = value[:1]
    if first in "\"'":
        end = _closing_quote(value)
        if end is None:
            raise ValueError(f"line {number}: the quoted value {_shown(value)} goes on over lines, which is not read: "
                             "write it on one line")
        if value[end + 1:].strip():
            raise ValueError(f"line {number}: {_shown(value)} goes on after its closing quote")
        body = value[1:end]
        return body.replace("''", "'") if first == "'" else _unescaped(body, number)
    refusals = {"&": "anchors (&name) are not read: write the values out in full",
                "*": "aliases (*name) are not read: write the values out in full",
                "{": "flow mappings {key: value, ...} are not read: write one 'key: value' a line (block style)",
                "|": "block scalars (| or >) are not read: write the value on the key's line",
                ">": "block scalars (| or >) are not read: write the value on the key's line",
                "!": "tags before a value (!!str, !!float) are not read: write the value alone"}
    if first in refusals:
        raise ValueError(f"line {number}: {_shown(value)}: {refusals[first]}")
    return value


def _unescaped(body: str, number: int) -> str:
    """The text of a double-quoted YAML scalar's ``body`` (between its quotes) with its escapes decoded;
    ValueError naming line ``number`` for an unknown or cut escape."""
    out, i = [], 0
    while i < len(body):
        char = body[i]
        if char != "\\":
            out.append(char)
            i += 1
            continue
        code = body[i + 1:i + 2]
        digits = _HEX_ESCAPES.get(code)
        if digits is not None:
            hex_digits = body[i + 2:i + 2 + digits]
            if len(hex_digits) != digits or any(c not in "0123456789abcdefABCDEF" for c in hex_digits):
                raise ValueError(f"line {number}: the escape {body[i:i + 2 + digits]!r} needs {digits} hex digits")
            out.append(chr(int(hex_digits, 16)))
            i += 2 + digits
        elif code in _ESCAPES:
            out.append(_ESCAPES[code])
            i += 2
        else:
            raise ValueError(f"line {number}: {body[i:i + 2]!r} is no YAML escape (a '\\' in a double-quoted "
                             "value starts one: write '\\\\' for a backslash, or use single quotes)")
    return "".join(out)


def _yaml_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` of a small YAML file without comments and blank lines, a flow list ``[...]`` that
    goes on over several lines (PyYAML wraps them at 80 columns, OpenCV's FileStorage too) joined into its first
    line (brackets inside quotes do not count). Directives (``%YAML``) before the document and the markers
    ``---`` / ``...`` around it are skipped. ValueError naming the line for a tab in the indentation (YAML
    forbids it), a second document after ``---`` / ``...`` (its keys would override the first's), and a ``[``
    never closed."""
    lines: list[tuple[int, str]] = []
    depth, opened_at, ended_at = 0, 0, None           # "[" not closed yet; its line; where a document ended
    for number, raw in enumerate(text.splitlines(), 1):
        line, code = _scan(raw)
        line = line.rstrip()
        if not line.strip():
            continue
        if depth == 0:
            if "\t" in line[:len(line) - len(line.lstrip(" \t"))]:
                raise ValueError(f"line {number} is indented with a tab, which YAML does not allow (a YAML reader "
                                 "refuses it too): indent with spaces")
            if line.startswith("%") and not lines:
                continue
            if line in ("---", "...") or line.startswith("--- "):
                ended_at = number if lines else ended_at
                continue
            if ended_at is not None:
                raise ValueError(f"line {number}: a second YAML document begins after line {ended_at} ('---' or "
                                 "'...'), which is not read (its keys would override the first's): keep one "
                                 "calibration a file (rostopic echo -n 1 prints one message)")
            lines.append((number, line))
            opened_at = number
        else:
            lines[-1] = (lines[-1][0], lines[-1][1] + " " + line.strip())
        depth += code.count("[") - code.count("]")
    if depth > 0:
        raise ValueError(f"line {opened_at}: a '[' is never closed")
    return lines


def _scan(line: str) -> tuple[str, str]:
    """``(line without its comment, the same with quoted text blanked)`` of a YAML line. A comment runs from a
    ``#`` at the line's start or after a space or tab, outside quotes (YAML's rule: ``"cam #1"`` and ``a#b`` are
    values, not a value and a comment). A quote opens a quoted scalar only where a value, key or list item
    starts (after ``:``, ``-``, ``[``, ``,``, ``{`` and spaces, or at the line's start); ``\\`` escapes the next
    character within double quotes, ``''`` is a quote within single quotes.

    >>> _scan('rostopic: "/cam #1/[left" # the left camera'), _scan("name: a#b Bob's # c")[0]
    (('rostopic: "/cam #1/[left" ', 'rostopic: "               '), "name: a#b Bob's ")
    """
    quote, i, code = None, 0, list(line)
    while i < len(line):
        char = line[i]
        before = line[i - 1] if i else " "
        if quote is not None:
            code[i] = " "
            if char == "\\" and quote == '"' or char == "'" == quote and line[i + 1:i + 2] == "'":
                i += 1                                  # an escaped character, a quote too
                code[i:i + 1] = [" "] * len(code[i:i + 1])
            elif char == quote:
                quote = None
        elif char in "\"'" and (not line[:i].strip() or line[:i].rstrip()[-1] in ":[,-{"):
            quote = char
        elif char == "#" and before in " \t":
            return line[:i], "".join(code[:i])
        i += 1
    return line, "".join(code)


#: ROS camera_info's names of OpenCV's radtan model (sensor_msgs/distortion_models.h): ``plumb_bob`` (k1 k2 p1 p2
#: k3) and ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6); ROS's ``image_geometry`` hands either's ``D`` to
#: OpenCV as it is (empty: no distortion), so 4, 5 or 8 coefficients are read for both.
ROS_RADTAN_MODELS = ("plumb_bob", "rational_polynomial")


def _ros_camera_info(path: Path, tree: dict, camera: str, flat) -> dict[str, str]:
    """The keys :func:`read_calibration` reads, of a ROS ``camera_info`` YAML (what ``camera_calibration`` and
    ``rpg_dvs_ros`` write: ``image_width``, ``image_height``, ``camera_matrix``, ``distortion_model``,
    ``distortion_coefficients``, ``rectification_matrix``, ``projection_matrix``, each matrix as ``data: [...]``,
    row-major): one camera (``camera`` other than ``cam0`` refused); a skewed ``camera_matrix`` refused."""
    if camera != "cam0":
        raise ValueError(f"{path} calibrates one camera (ROS camera_info): camera {camera!r} (--calib-camera) chooses "
                         "one of a DSEC cam_to_cam.yaml or a Kalibr camchain .yaml; leave it out")

    def data(key: str) -> str | None:
        entry = tree.get(key)
        return flat(entry).get("data") if isinstance(entry, dict) else None

    try:
        m = _numbers(data("camera_matrix") or "")
    except ValueError:
        m = []
    if len(m) != 9 or m[1] != 0 or m[3] != 0 or m[6:] != [0, 0, 1]:
        raise ValueError(f"{path}: camera_matrix data must be the 9 numbers of [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                         f"(ROS camera_info), got {data('camera_matrix')!r}")
    values = {"camera_matrix": f"[{m[0]!r}, {m[4]!r}, {m[2]!r}, {m[5]!r}]"}
    if (coefficients := data("distortion_coefficients")) is not None:
        values["distortion_coeffs"] = coefficients
    if "distortion_model" in tree and isinstance(tree["distortion_model"], str):
        values["distortion_model"] = tree["distortion_model"]
        if tree["distortion_model"] in ROS_RADTAN_MODELS:     # OpenCV's coefficients, read by their number
            values["distortion_model"], values["distortion_model_ros"] = "radtan", tree["distortion_model"]
    if "image_width" in tree and "image_height" in tree:
        values["resolution"] = f"[{tree['image_width']}, {tree['image_height']}]"
    for key in ("rectification_matrix", "projection_matrix"):
        if (matrix := data(key)) is not None:
            values[key] = matrix
    if "rostopic" in tree and isinstance(tree["rostopic"], str):
        values["rostopic"] = tree["rostopic"]
    return values


def _dsec_rectification(tree: dict, camera: str, flat) -> dict[str, str]:
    """The rectification of a raw camera ``camN`` of a DSEC ``cam_to_cam.yaml`` (``tree``, :func:`_yaml_tree`) as
    :func:`read_calibration` reads a camchain's: ``rectification_matrix`` = ``extrinsics/R_rectN`` (3x3, camN to
    camRectN) and ``projection_matrix`` = the pinhole matrix of ``intrinsics/camRectN``'s ``camera_matrix: [fx, fy,
    cx, cy]`` [px], the frame of DSEC's disparity maps and ``rectify_map.h5`` (``cv2.undistortPoints(..., R=R_rectN,
    P=K_rectN)``); empty for another camera (``camRectN``: already rectified) or a file without both."""
    number = camera[3:] if camera.startswith("cam") and camera[3:].isdigit() else None
    extrinsics, intrinsics = tree.get("extrinsics"), tree.get("intrinsics")
    if number is None or not isinstance(extrinsics, dict) or not isinstance(intrinsics, dict):
        return {}
    rotation, rectified = extrinsics.get(f"R_rect{number}"), intrinsics.get(f"camRect{number}")
    if rotation is None or not isinstance(rectified, dict) or "camera_matrix" not in flat(rectified):
        return {}
    try:
        fx, fy, cx, cy = _numbers(flat(rectified)["camera_matrix"])
    except ValueError:
        return {"projection_matrix": flat(rectified)["camera_matrix"],   # refused by read_calibration, named
                "projection_matrix_name": f"intrinsics/camRect{number}'s camera_matrix"}
    rows = "[" + ", ".join(rotation) + "]" if isinstance(rotation, list) else str(rotation)
    return {"rectification_matrix": rows, "projection_matrix": f"[{fx!r}, 0, {cx!r}, 0, {fy!r}, {cy!r}, 0, 0, 1]",
            "rectified_from": f"extrinsics/R_rect{number} and intrinsics/camRect{number}",
            "rectification_matrix_name": f"extrinsics/R_rect{number} (the rectification of {camera})",
            "projection_matrix_name": f"intrinsics/camRect{number}'s camera_matrix"}


def _echoed_camera_info(tree: dict) -> dict:
    """``tree`` (:func:`_yaml_tree`) of a CameraInfo message as ``rostopic echo`` (``K``, ``D``, ``R``, ``P``,
    ``width``, ``height``) or ``ros2 topic echo`` (lower case) print it, in the layout of a camera_info YAML
    (``camera_matrix: {data: ...}``, ...); any other tree as it is."""
    names = {key.lower(): key for key in tree if key in ("K", "D", "R", "P", "k", "d", "r", "p")}
    if not {"k", "d", "p"} <= set(names) or "camera_matrix" in tree:
        return tree

    def data(key: str) -> dict[str, str]:
        value = tree[names[key]]
        return {"data": "[" + ", ".join(value) + "]" if isinstance(value, list) else str(value)}

    echoed = {"camera_matrix": data("k"), "distortion_coefficients": data("d"), "projection_matrix": data("p")}
    if "r" in names:
        echoed["rectification_matrix"] = data("r")
    if isinstance(tree.get("distortion_model"), str):
        echoed["distortion_model"] = tree["distortion_model"]
    if isinstance(tree.get("width"), str) and isinstance(tree.get("height"), str):
        echoed["image_width"], echoed["image_height"] = tree["width"], tree["height"]
    return echoed


def _yaml_intrinsics(path: Path, text: str, camera: str) -> dict[str, str]:
    """The intrinsics of ``camera`` in a DSEC ``cam_to_cam.yaml`` (``intrinsics/<camera>``, with
    ``camera_matrix``), a Kalibr camchain (``<camera>`` with ``intrinsics: [fx, fy, cx, cy]``, given back as
    ``camera_matrix``) or a ROS ``camera_info`` YAML (:func:`_ros_camera_info`), as ``key: text``; lists in flow
    or block style; ValueError naming the file and line for what :func:`_yaml_tree` does not read."""
    try:
        tree = _yaml_tree(text)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None

    def flat(values: dict) -> dict[str, str]:
        return {key: "[" + ", ".join(value) + "]" if isinstance(value, list) else value
                for key, value in values.items() if not isinstance(value, dict)}

    tree = _echoed_camera_info(tree)
    if isinstance(tree.get("camera_matrix"), dict) and "data" in tree["camera_matrix"]:
        return _ros_camera_info(path, tree, camera, flat)
    dsec = tree.get("intrinsics")
    if isinstance(dsec, dict):
        if isinstance(dsec.get(camera), dict):
            return {**flat(dsec[camera]), **_dsec_rectification(tree, camera, flat)}
        found = sorted(key for key, value in dsec.items() if isinstance(value, dict)) or ["none"]
    else:
        kalibr = {key: value for key, value in tree.items() if isinstance(value, dict) and "intrinsics" in value}
        if camera in kalibr:
            values = flat(kalibr[camera])
            model = values.get("camera_model", "pinhole").strip()
            if model != "pinhole":
                raise ValueError(f"{path}: {camera} has camera_model {model!r}; only pinhole cameras are supported")
            values["camera_matrix"] = values.pop("intrinsics")
            return values
        found = sorted(kalibr) or ["none"]
    raise ValueError(f"{path}: no intrinsics/{camera} (cameras found: {', '.join(found)}); "
                     "choose one with --calib-camera")
