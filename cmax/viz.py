"""Pictures of events, event volumes and depth maps (OpenCV only; no plotting library).

Every function returns an (H, W, 3) uint8 image in BGR order (OpenCV's), so
that pictures can be tiled with :func:`hstack` / :func:`vstack` and written
with :func:`save_png`. Conventions: ON events blue, OFF events red on white;
signed quantities (event volumes) on a blue-white-red scale symmetric about
zero; depth on the magma scale of inverse depth (near = bright), NaN black.
"""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "event_frame_image", "iwe_image", "signed_image", "voxel_grid_image", "depth_image", "robust_max",
    "titled", "hstack", "vstack", "save_png",
]

_WHITE = 255
_TITLE_HEIGHT = 22


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


def event_frame_image(counts: np.ndarray, *, percentile: float = 99.0) -> np.ndarray:
    """Picture of per-polarity event counts (2, H, W): ON blue, OFF red, white background.

    Colour strength grows with the count and saturates at the given
    percentile of the non-zero counts.
    """
    counts = np.asarray(counts, dtype=np.float32)
    if counts.ndim != 3 or counts.shape[0] != 2:
        raise ValueError(f"counts must have shape (2, H, W), got {counts.shape}")
    _check_finite(counts, "counts")
    scale = robust_max(counts.sum(axis=0), percentile)
    off = np.clip(counts[0] / scale, 0, 1)
    on = np.clip(counts[1] / scale, 0, 1)
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


def signed_image(values: np.ndarray, *, scale: float | None = None) -> np.ndarray:
    """Blue (positive) - white (zero) - red (negative) picture of an (H, W) array."""
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ValueError(f"values must have shape (H, W), got {values.shape}")
    _check_finite(values, "values")
    scale = robust_max(values) if scale is None else float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale}")
    level = np.clip(values / scale, -1, 1)
    image = np.full(values.shape + (3,), float(_WHITE), np.float32)
    positive, negative = np.clip(level, 0, 1), np.clip(-level, 0, 1)
    image[..., 0] -= _WHITE * negative
    image[..., 1] -= _WHITE * (positive + negative)
    image[..., 2] -= _WHITE * positive
    return np.clip(image, 0, 255).astype(np.uint8)


def voxel_grid_image(volume: np.ndarray, *, gap: int = 4) -> np.ndarray:
    """The B bins of an event volume (B, H, W) side by side, on one symmetric colour scale."""
    volume = np.asarray(volume, dtype=np.float32)
    if volume.ndim != 3:
        raise ValueError(f"volume must have shape (B, H, W), got {volume.shape}")
    if not volume.shape[0]:
        raise ValueError("volume must have at least one bin, got shape (0, H, W)")
    _check_finite(volume, "volume")
    scale = robust_max(volume)
    tiles = [titled(signed_image(b, scale=scale), f"bin {i}") for i, b in enumerate(volume)]
    return hstack(tiles, gap=gap)


def depth_image(
    depth: np.ndarray, *, depth_range: tuple[float, float] | None = None
) -> np.ndarray:
    """Depth (H, W) in metres as magma-coloured inverse depth; NaN or <= 0 is black."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must have shape (H, W), got {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0)
    if depth_range is None:
        if valid.any():
            depth_range = (float(np.percentile(depth[valid], 1)), float(np.percentile(depth[valid], 99)))
        else:
            depth_range = (1.0, 2.0)
    near, far = depth_range
    if not 0 < near < far:
        raise ValueError(f"depth_range must satisfy 0 < near < far, got {depth_range}")
    inverse = np.zeros_like(depth)
    inverse[valid] = 1.0 / depth[valid]
    level = np.clip((inverse - 1.0 / far) / (1.0 / near - 1.0 / far), 0, 1)
    image = cv2.applyColorMap((255 * level).astype(np.uint8), cv2.COLORMAP_MAGMA)
    image[~valid] = 0
    return image


def titled(image: np.ndarray, title: str) -> np.ndarray:
    """``image`` with a white strip above it holding ``title``."""
    image = _check_picture(image)
    strip = np.full((_TITLE_HEIGHT, image.shape[1], 3), _WHITE, np.uint8)
    cv2.putText(strip, title, (4, _TITLE_HEIGHT - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
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
    """Images side by side, top-aligned, separated by ``gap`` white pixels."""
    images = _check_pictures(images)
    height = max(image.shape[0] for image in images)
    parts: list[np.ndarray] = []
    for i, image in enumerate(images):
        if i:
            parts.append(np.full((height, gap, 3), _WHITE, np.uint8))
        parts.append(_pad_to(image, height, image.shape[1]))
    return np.hstack(parts)


def vstack(images: list[np.ndarray], *, gap: int = 4) -> np.ndarray:
    """Images one above the other, left-aligned, separated by ``gap`` white pixels."""
    images = _check_pictures(images)
    width = max(image.shape[1] for image in images)
    parts: list[np.ndarray] = []
    for i, image in enumerate(images):
        if i:
            parts.append(np.full((gap, width, 3), _WHITE, np.uint8))
        parts.append(_pad_to(image, image.shape[0], width))
    return np.vstack(parts)


def save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a BGR or grey uint8 image as PNG atomically (temporary name, then rename)."""
    path = Path(path)
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None].repeat(3, axis=2)
    image = _check_picture(image)
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise ValueError(f"OpenCV could not encode an image of shape {image.shape} as PNG")
    partial = path.with_name(path.name + ".partial")
    try:
        partial.write_bytes(encoded.tobytes())
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path
