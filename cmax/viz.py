"""Pictures of events, event volumes and depth maps (OpenCV only; no plotting library).

Every function returns an (H, W, 3) uint8 image in BGR order (OpenCV's), so
that pictures can be tiled with :func:`hstack` / :func:`vstack` and written
with :func:`save_image` (PNG or JPEG, by the file's extension). Conventions:

- events: ON blue, OFF red on white; :func:`event_panel` adds the ON/OFF legend;
- signed quantities (event volumes): blue-white-red, symmetric about zero;
- depth: the magma colour map of inverse depth (near = bright) on a
  :class:`DepthScale` in metres, which :func:`depth_panel` draws as a colour bar
  beside the map; give several maps one scale (``DepthScale.from_depths`` over
  all of them) so that one depth has one colour in every picture. "No estimate"
  (NaN, <= 0) is a grey hatch, :data:`NO_DEPTH_BGR` and :data:`NO_DEPTH_HATCH_BGR`,
  colours far from every colour of the map, so it cannot be read as a depth.

Colour bars and legends are drawn with OpenCV: matplotlib would add a
dependency (it is not installed with the project) for what is a gradient, a few
tick labels and two swatches.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np

__all__ = [
    "event_frame_image", "iwe_image", "signed_image", "signed_colour_bar", "voxel_grid_image", "depth_image",
    "robust_max",
    "titled", "hstack", "vstack", "save_png", "save_image", "DepthScale", "depth_colour_bar", "depth_panel",
    "event_panel", "grid", "ON_BGR", "OFF_BGR", "NO_DEPTH_BGR", "NO_DEPTH_HATCH_BGR", "IMAGE_SUFFIXES",
    "MIN_PICTURE_WIDTH", "readable_zoom", "enlarge",
]

_WHITE = 255
_TITLE_HEIGHT = 22
_FONT = cv2.FONT_HERSHEY_SIMPLEX
#: Colours (BGR) of ON and OFF events in :func:`event_frame_image`.
ON_BGR = (255, 0, 0)
OFF_BGR = (0, 0, 255)
#: The two greys of the "no estimate" hatch (a faint one, so that sparse maps stay readable): at least
#: 65 levels (in some channel) from every magma colour.
NO_DEPTH_BGR = (150, 150, 150)
NO_DEPTH_HATCH_BGR = (170, 170, 170)
#: Extensions :func:`save_image` writes, and how: OpenCV's encoder of that name.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: Narrowest map in a saved picture [px]: a smaller sensor's maps are drawn enlarged (:func:`readable_zoom`), so
#: that their titles and colour bars stay readable.
MIN_PICTURE_WIDTH = 320


def readable_zoom(width: int) -> int:
    """The smallest whole factor that draws a map ``width`` pixels wide at least :data:`MIN_PICTURE_WIDTH`
    wide (1 for a wide enough map).

    >>> readable_zoom(64), readable_zoom(346)
    (5, 1)
    """
    return max(1, -(-MIN_PICTURE_WIDTH // int(width)))


def enlarge(values: np.ndarray, zoom: int) -> np.ndarray:
    """``values`` (H, W) with each pixel a ``zoom x zoom`` block (H zoom, W zoom); ``zoom`` a whole number >= 1.

    >>> import numpy as np
    >>> enlarge(np.array([[1, 2]]), 2).tolist()
    [[1, 1, 2, 2], [1, 1, 2, 2]]
    """
    if isinstance(zoom, bool) or not isinstance(zoom, (int, np.integer)) or zoom < 1:
        raise ValueError(f"zoom must be a whole number >= 1, got {zoom!r}")
    return values if zoom == 1 else np.repeat(np.repeat(values, zoom, axis=0), zoom, axis=1)


def _check_finite(values: np.ndarray, name: str) -> None:
    if not np.isfinite(values).all():
        raise ValueError(f"{name} must be finite (it holds NaN or infinite values)")


def _check_picture(image: object, name: str = "image") -> np.ndarray:
    """A BGR picture: a non-empty (H, W, 3) uint8 array."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or not image.shape[0] or not image.shape[1]:
        raise ValueError(f"{name} must be a non-empty (H, W, 3) BGR picture, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise TypeError(f"{name} must be uint8, got {image.dtype}")
    return image


def robust_max(values: np.ndarray, percentile: float = 99.0) -> float:
    """The ``percentile`` of the non-zero ``|values|`` (1 when all are zero): where a picture's colours saturate."""
    nonzero = np.abs(values[values != 0])
    if not nonzero.size:
        return 1.0
    return float(max(np.percentile(nonzero, percentile), 1e-12))


def _check_gamma(gamma: float) -> float:
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float, np.integer, np.floating)) or not 0 < gamma <= 1:
        raise ValueError(f"gamma must be a number in (0, 1], got {gamma!r}")
    return float(gamma)


def event_frame_image(counts: np.ndarray, *, percentile: float = 99.0, gamma: float = 1.0) -> np.ndarray:
    """Picture of per-polarity event counts (2, H, W): ON blue, OFF red, white background.

    Colour strength grows with the count, as ``(count / scale) ** gamma``, and
    saturates at ``scale``, the given percentile of the non-zero per-pixel
    counts (a lower percentile and ``gamma < 1`` keep a few very active pixels,
    a flickering lamp, from washing out the rest).
    """
    counts = np.asarray(counts, dtype=np.float32)
    if counts.ndim != 3 or counts.shape[0] != 2:
        raise ValueError(f"counts must have shape (2, H, W), got {counts.shape}")
    _check_finite(counts, "counts")
    gamma = _check_gamma(gamma)
    total = counts.sum(axis=0)
    scale = robust_max(total, percentile)
    strength = np.clip(total / scale, 0, 1) ** gamma
    share = np.divide(counts, total, out=np.zeros_like(counts), where=total > 0)
    off, on = strength * share[0], strength * share[1]
    image = np.full(counts.shape[1:] + (3,), float(_WHITE), np.float32)
    # Blue (BGR 255, 0, 0) for ON, red (0, 0, 255) for OFF; mixed pixels turn purple.
    image[..., 0] -= _WHITE * off
    image[..., 1] -= _WHITE * np.clip(on + off, 0, 1)
    image[..., 2] -= _WHITE * on
    return np.clip(image, 0, 255).astype(np.uint8)


def iwe_image(image: np.ndarray, *, scale: float | None = None, percentile: float = 99.0) -> np.ndarray:
    """Picture (H, W, 3) uint8 of an image of warped events (H, W) (counts >= 0): dark ink on white.

    The ink saturates at ``scale`` (default: the ``percentile`` of the
    non-zero values); give one ``scale`` to draw several IWEs alike.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError(f"image must have shape (H, W), got {image.shape}")
    _check_finite(image, "image")
    scale = robust_max(image, percentile) if scale is None else float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale}")
    grey = (255 - np.clip(image / scale, 0, 1) * 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def signed_image(values: np.ndarray, *, scale: float | None = None, gamma: float = 1.0) -> np.ndarray:
    """Blue (positive) - white (zero) - red (negative) picture of an (H, W) array.

    Colour strength is ``(|value| / scale) ** gamma``, saturating at ``scale``
    (default: the 99th percentile of the non-zero ``|values|``).
    """
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ValueError(f"values must have shape (H, W), got {values.shape}")
    _check_finite(values, "values")
    gamma = _check_gamma(gamma)
    scale = robust_max(values) if scale is None else float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale}")
    level = np.sign(values) * np.clip(np.abs(values) / scale, 0, 1) ** gamma
    image = np.full(values.shape + (3,), float(_WHITE), np.float32)
    positive, negative = np.clip(level, 0, 1), np.clip(-level, 0, 1)
    image[..., 0] -= _WHITE * negative
    image[..., 1] -= _WHITE * (positive + negative)
    image[..., 2] -= _WHITE * positive
    return np.clip(image, 0, 255).astype(np.uint8)


def signed_colour_bar(height: int, scale: float, *, gamma: float = 1.0, font_scale: float = 0.4,
                      unit: str = "") -> np.ndarray:
    """Vertical colour bar (height, w, 3) of :func:`signed_image`'s map: ``+scale`` (blue, top), 0 (white), and
    ``-scale`` (red, bottom), labelled at the ends and at zero in ``unit`` (text of ``font_scale``); the ends saturate (``>=``); ``gamma``
    as :func:`signed_image`."""
    if isinstance(height, bool) or not isinstance(height, (int, np.integer)) or height < 40:
        raise ValueError(f"height must be an integer >= 40 px, got {height!r}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale}")
    thickness = _thickness(font_scale)
    line = int(round(18 * font_scale / 0.4))
    bar_width = max(12, line)
    labels = [f">= +{scale:.3g} {unit}".rstrip(), f"0 {unit}".rstrip(), f"<= -{scale:.3g} {unit}".rstrip()]
    width = bar_width + 8 + max(_text_width(text, font_scale) for text in labels) + 4
    image = np.full((height, width, 3), _WHITE, np.uint8)
    top = line // 2
    bar_height = height - line
    values = np.linspace(scale, -scale, bar_height, dtype=np.float32)
    image[top: top + bar_height, :bar_width] = signed_image(np.repeat(values[:, None], bar_width, axis=1),
                                                            scale=scale, gamma=gamma)
    for k, text in enumerate(labels):
        row = top + int(round(k * (bar_height - 1) / 2))
        image[row, bar_width: bar_width + 4] = 0
        cv2.putText(image, text, (bar_width + 6, row + line // 3), _FONT, font_scale, (0, 0, 0), thickness,
                    cv2.LINE_AA)
    return image


def voxel_grid_image(volume: np.ndarray, *, gap: int = 4, columns: int | None = None,
                     percentile: float = 99.0, gamma: float = 1.0, shrink: int = 1,
                     unit: str | None = "events") -> np.ndarray:
    """The B bins of an event volume (B, H, W) on one symmetric colour scale (the ``percentile`` of
    the non-zero ``|values|`` of all bins, ``gamma`` as :func:`signed_image`), side by side or in rows of ``columns``
    ``gap`` px apart, each bin
    reduced ``shrink`` times (area average of the picture) for wide sensors; with a colour bar of that
    scale labelled in ``unit`` beside them (None: no bar)."""
    volume = np.asarray(volume, dtype=np.float32)
    if volume.ndim != 3:
        raise ValueError(f"volume must have shape (B, H, W), got {volume.shape}")
    if not volume.shape[0]:
        raise ValueError("volume must have at least one bin, got shape (0, H, W)")
    _check_finite(volume, "volume")
    if isinstance(shrink, bool) or not isinstance(shrink, (int, np.integer)) or shrink < 1:
        raise ValueError(f"shrink must be an integer >= 1, got {shrink!r}")
    scale = robust_max(volume, percentile)
    tiles = []
    for i, values in enumerate(volume):
        tile = signed_image(values, scale=scale, gamma=gamma)
        if shrink > 1:
            size = (max(1, tile.shape[1] // shrink), max(1, tile.shape[0] // shrink))
            tile = cv2.resize(tile, size, interpolation=cv2.INTER_AREA)
        tiles.append(titled(tile, f"bin {i}"))
    picture = grid(tiles, len(tiles) if columns is None else columns, gap=gap)
    if unit is None:
        return picture
    bar = signed_colour_bar(max(tiles[0].shape[0], 40), scale, gamma=gamma,
                            font_scale=_font_scale(tiles[0].shape[1]) * 0.9, unit=unit)
    return hstack([picture, bar], gap=gap)


@dataclass(frozen=True)
class DepthScale:
    """The depths [m] at the two ends of the colour map: ``near`` brightest, ``far`` darkest.

    Colours are spaced evenly in inverse depth. Build one scale for a whole run
    (``DepthScale.from_depths([d0, d1, ...])``) and pass it to every picture, so
    that the same depth has the same colour in every window.
    """

    near: float
    far: float

    def __post_init__(self) -> None:
        near, far = self.near, self.far
        if not all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                   for v in (near, far)):
            raise TypeError(f"near and far must be numbers of metres, got {near!r}, {far!r}")
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
            raise ValueError(f"depth range must satisfy 0 < near < far (finite metres), got ({near}, {far})")
        object.__setattr__(self, "near", float(near))
        object.__setattr__(self, "far", float(far))

    @classmethod
    def from_depths(cls, depths: np.ndarray | Iterable[np.ndarray],
                    percentiles: tuple[float, float] = (1.0, 99.0)) -> "DepthScale":
        """The ``percentiles`` of the positive finite depths of one map or of several (all pooled).

        Raises ``ValueError`` when no map holds a depth. A single depth value gives a
        range 1% either side of it.
        """
        maps = [depths] if isinstance(depths, np.ndarray) else list(depths)
        values = [np.asarray(d, np.float64).ravel() for d in maps if d is not None]
        values = np.concatenate(values) if values else np.empty(0)
        values = values[np.isfinite(values) & (values > 0)]
        if not values.size:
            raise ValueError("depths hold no positive finite depth to take a colour scale from")
        low, high = (float(v) for v in np.percentile(values, percentiles))
        if not low < high:
            low, high = low / 1.01, high * 1.01
        return cls(low, high)

    @classmethod
    def of(cls, scale: "DepthScale | tuple[float, float] | None", depth: np.ndarray) -> "DepthScale":
        """``scale`` as a DepthScale: a DepthScale, ``(near, far)``, or None (the map's own 1-99%,
        or 1-2 m when it holds no depth)."""
        if isinstance(scale, DepthScale):
            return scale
        if scale is None:
            try:
                return cls.from_depths(depth)
            except ValueError:
                return cls(1.0, 2.0)
        near, far = scale
        return cls(near, far)

    def level(self, depth: np.ndarray) -> np.ndarray:
        """Position of each depth on the map, 0 (far) .. 1 (near), clipped; NaN where there is no depth."""
        depth = np.asarray(depth, np.float64)
        valid = np.isfinite(depth) & (depth > 0)
        inverse = np.divide(1.0, depth, out=np.full(depth.shape, np.nan), where=valid)
        level = (inverse - 1.0 / self.far) / (1.0 / self.near - 1.0 / self.far)
        return np.clip(level, 0.0, 1.0)

    def ticks(self, count: int = 5) -> np.ndarray:
        """``count`` depths [m] from near to far, evenly spaced in inverse depth (as the colours)."""
        return 1.0 / np.linspace(1.0 / self.near, 1.0 / self.far, count)


def _no_depth_hatch(shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) diagonal grey stripes, the picture of "no estimate"."""
    rows, cols = np.indices(shape)
    stripes = (rows + cols) % 6 < 2
    image = np.empty(shape + (3,), np.uint8)
    image[...] = NO_DEPTH_BGR
    image[stripes] = NO_DEPTH_HATCH_BGR
    return image


def depth_image(
    depth: np.ndarray, scale: "DepthScale | tuple[float, float] | None" = None, *,
    depth_range: tuple[float, float] | None = None,
) -> np.ndarray:
    """Depth (H, W) in metres as magma-coloured inverse depth on ``scale``; NaN or <= 0 is a grey hatch.

    ``scale`` (or its older name ``depth_range``): a :class:`DepthScale`, ``(near, far)`` metres,
    or None for the map's own 1st-99th percentiles (pass one scale to draw several maps alike).
    """
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    if scale is not None and depth_range is not None:
        raise TypeError("give scale or depth_range, not both")
    scale = DepthScale.of(scale if scale is not None else depth_range, depth)
    level = scale.level(depth)
    valid = np.isfinite(level)
    image = cv2.applyColorMap((255 * np.where(valid, level, 0)).astype(np.uint8), cv2.COLORMAP_MAGMA)
    image[~valid] = _no_depth_hatch(depth.shape)[~valid]
    return image


def _font_scale(width: int) -> float:
    """Text size for a picture ``width`` px wide: 0.45 up to 640 px, growing with the width beyond."""
    return 0.45 * max(1.0, width / 640.0)


def _thickness(font_scale: float) -> int:
    """Stroke width [px] of text at ``font_scale``: 2 from 0.8 up, so that large text stays legible."""
    return 1 if font_scale < 0.8 else 2


def _text_width(text: str, font_scale: float) -> int:
    """Width [px] of ``text`` as drawn (at the stroke width :func:`_thickness` gives)."""
    return cv2.getTextSize(text, _FONT, font_scale, _thickness(font_scale))[0][0]


def depth_bar_labels(depths: np.ndarray, unit: str = "m") -> list[str]:
    """Labels of a depth colour bar's ticks, near to far: the ends read ``<=`` and ``>=``, because
    :meth:`DepthScale.level` clips, so a depth nearer than the near end takes its colour (and one farther
    than the far end the far colour).

    >>> import numpy as np
    >>> depth_bar_labels(np.array([1.0, 2.0, 4.0]))
    ['<= 1 m', '2 m', '>= 4 m']
    """
    labels = [f"{d:.3g} {unit}".rstrip() for d in depths]
    if len(labels) >= 2:
        labels[0], labels[-1] = f"<= {labels[0]}", f">= {labels[-1]}"
    return labels


def depth_colour_bar(height: int, scale: DepthScale, *, ticks: int = 5, font_scale: float = 0.4,
                     unit: str = "m") -> np.ndarray:
    """Vertical colour bar (height, w, 3) of ``scale`` labelled in ``unit`` (metres; ``""`` for
    depth up to scale; ``ticks`` labels, text of ``font_scale``), near at the top, with the "no estimate" swatch
    below it labelled ``n/a``; its
    ends saturate (``<=`` near, ``>=`` far: :func:`depth_bar_labels`)."""
    if isinstance(height, bool) or not isinstance(height, (int, np.integer)) or height < 40:
        raise ValueError(f"height must be an integer >= 40 px, got {height!r}")
    if not isinstance(scale, DepthScale):
        raise TypeError(f"scale must be a DepthScale, got {type(scale).__name__}")
    thickness = _thickness(font_scale)
    line = int(round(18 * font_scale / 0.4))
    bar_width = max(12, line)
    swatch = line + 2
    bar_height = height - swatch - 6 - line // 2
    depths = scale.ticks(ticks)
    if not isinstance(unit, str):
        raise TypeError(f"unit must be a string, got {type(unit).__name__}")
    labels = depth_bar_labels(depths, unit) + ["n/a"]
    width = bar_width + 8 + max(_text_width(text, font_scale) for text in labels) + 4
    image = np.full((height, width, 3), _WHITE, np.uint8)
    top = line // 2
    values = 1.0 / np.linspace(1.0 / scale.near, 1.0 / scale.far, bar_height)
    image[top: top + bar_height, :bar_width] = depth_image(
        np.repeat(values[:, None], bar_width, axis=1), scale)
    for k, depth in enumerate(depths):
        row = top + int(round(k * (bar_height - 1) / (ticks - 1)))
        image[row, bar_width: bar_width + 4] = 0
        cv2.putText(image, labels[k], (bar_width + 6, row + line // 3), _FONT, font_scale, (0, 0, 0), thickness,
                    cv2.LINE_AA)
    y0 = height - swatch
    image[y0:, :bar_width] = _no_depth_hatch((swatch, bar_width))
    cv2.putText(image, "n/a", (bar_width + 6, height - 3), _FONT, font_scale, (0, 0, 0), thickness, cv2.LINE_AA)
    return image


def depth_panel(depth: np.ndarray, scale: "DepthScale | tuple[float, float] | None" = None,
                title: str = "depth", *, unit: str = "m") -> np.ndarray:
    """A depth map ``depth`` (H, W) [``unit``, NaN: no estimate] with its ``title`` and a colour bar in ``unit``
    (metres by default; ``""`` for depth up to scale) (``scale`` as in :func:`depth_image`): a BGR uint8
    picture (h, w, 3)."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    scale = DepthScale.of(scale, depth)
    image = depth_image(depth, scale)
    font = _font_scale(depth.shape[1]) * 0.9
    bar = depth_colour_bar(max(depth.shape[0], 40), scale, font_scale=font, unit=unit)
    return titled(hstack([image, bar], gap=4), title)


def event_panel(counts: np.ndarray, title: str = "events", *, percentile: float = 99.0,
                gamma: float = 1.0) -> np.ndarray:
    """:func:`event_frame_image` of per-polarity ``counts`` (2, H, W) (``percentile``, ``gamma`` as there) with its
    ``title`` and an ON/OFF legend."""
    return titled(event_frame_image(counts, percentile=percentile, gamma=gamma), title,
                  legend=(("ON", ON_BGR), ("OFF", OFF_BGR)))


def _legend_width(legend: Sequence[tuple[str, tuple[int, int, int]]], font_scale: float, box: int) -> int:
    return sum(box + 4 + _text_width(label, font_scale) + 10 for label, _ in legend)


def _wrap(text: str, font_scale: float, width: int) -> list[str]:
    """``text`` broken at spaces into lines that fit ``width`` px (a word longer than that stays whole)."""
    lines: list[str] = []
    for word in text.split(" "):
        if lines and _text_width(f"{lines[-1]} {word}", font_scale) <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines or [""]


def titled(image: np.ndarray, title: str, *,
           legend: Sequence[tuple[str, tuple[int, int, int]]] = ()) -> np.ndarray:
    """``image`` with a white strip above it holding ``title`` and, right-aligned, a legend of
    ``(label, BGR colour)`` swatches. The text grows with the picture's width (readable when a wide
    picture is scaled down); a title wider than the picture is wrapped at spaces, and a legend that
    does not fit beside the title's last line goes on a line of its own."""
    image = _check_picture(image)
    width = image.shape[1]
    font = _font_scale(width)
    thickness = _thickness(font)
    line = int(round(_TITLE_HEIGHT * font / 0.45))
    box = int(round(10 * font / 0.45))
    lines = _wrap(title, font, width - 8)
    legend_width = _legend_width(legend, font, box) if legend else 0
    own_line = bool(legend) and 4 + _text_width(lines[-1], font) + 12 + legend_width > width
    strip = np.full((line * (len(lines) + own_line), width, 3), _WHITE, np.uint8)
    baseline = line - int(round(7 * font / 0.45))
    for k, text in enumerate(lines):
        cv2.putText(strip, text, (4, baseline + k * line), _FONT, font, (0, 0, 0), thickness, cv2.LINE_AA)
    if legend:
        y = baseline + line * (len(lines) - 1 + own_line)
        x = 4 if own_line else width - legend_width
        for label, colour in legend:
            cv2.rectangle(strip, (x, y - box), (x + box, y), tuple(int(c) for c in colour), -1)
            x += box + 4
            cv2.putText(strip, label, (x, y), _FONT, font, (0, 0, 0), thickness, cv2.LINE_AA)
            x += _text_width(label, font) + 10
    return np.vstack([strip, image])


def _pad_to(image: np.ndarray, height: int, width: int) -> np.ndarray:
    out = np.full((height, width, 3), _WHITE, np.uint8)
    out[: image.shape[0], : image.shape[1]] = image
    return out


def _check_pictures(images: list[np.ndarray]) -> list[np.ndarray]:
    images = list(images)
    if not images:
        raise ValueError("images must hold at least one picture")
    return [_check_picture(image, f"images[{i}]") for i, image in enumerate(images)]


def hstack(images: list[np.ndarray], *, gap: int = 4) -> np.ndarray:
    """``images`` (BGR uint8) side by side, top-aligned, separated by ``gap`` white pixels."""
    images = _check_pictures(images)
    height = max(image.shape[0] for image in images)
    parts: list[np.ndarray] = []
    for i, image in enumerate(images):
        if i:
            parts.append(np.full((height, gap, 3), _WHITE, np.uint8))
        parts.append(_pad_to(image, height, image.shape[1]))
    return np.hstack(parts)


def vstack(images: list[np.ndarray], *, gap: int = 4) -> np.ndarray:
    """``images`` (BGR uint8) one above the other, left-aligned, separated by ``gap`` white pixels."""
    images = _check_pictures(images)
    width = max(image.shape[1] for image in images)
    parts: list[np.ndarray] = []
    for i, image in enumerate(images):
        if i:
            parts.append(np.full((gap, width, 3), _WHITE, np.uint8))
        parts.append(_pad_to(image, image.shape[0], width))
    return np.vstack(parts)


def grid(images: list[np.ndarray], columns: int, *, gap: int = 4) -> np.ndarray:
    """``images`` (BGR uint8) in rows of ``columns``, left to right then top to bottom, ``gap`` px apart: one
    (h, w, 3) uint8 picture."""
    images = _check_pictures(images)
    if isinstance(columns, bool) or not isinstance(columns, (int, np.integer)) or columns < 1:
        raise ValueError(f"columns must be an integer >= 1, got {columns!r}")
    rows = [hstack(images[i: i + columns], gap=gap) for i in range(0, len(images), columns)]
    return vstack(rows, gap=gap)


def save_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write ``image``, (H, W, 3) BGR or (H, W) grey uint8, atomically in the format of ``path``'s extension
    (``.png``, or JPEG for ``.jpg``/``.jpeg``); any other extension is refused with ``ValueError``."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"cannot tell the picture format of {str(path)!r}: the file name must end in "
                         f"{', '.join(IMAGE_SUFFIXES)}, got {suffix or 'no extension'!r}")
    return _save_encoded(path, image, suffix)


def save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a BGR or grey uint8 image as PNG atomically (temporary name, then rename), whatever
    ``path``'s extension; :func:`save_image` follows the extension."""
    return _save_encoded(Path(path), image, ".png")


def _save_encoded(path: Path, image: np.ndarray, suffix: str) -> Path:
    """Encode ``image`` as ``suffix`` and write it under a temporary name, then rename."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None].repeat(3, axis=2)
    image = _check_picture(image)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix in (".jpg", ".jpeg") else []
    ok, encoded = cv2.imencode(suffix, np.ascontiguousarray(image), params)
    if not ok:
        raise ValueError(f"OpenCV could not encode an image of shape {image.shape} as {suffix}")
    from cmax.io.atomic import write_bytes_atomic  # a lock and a private temporary: no planted link followed

    return write_bytes_atomic(path, encoded.tobytes())
