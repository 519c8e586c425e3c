"""Procedural grey textures for synthetic scenes, and their mip-mapped atlas.

Every texture is a square ``(S, S)`` float32 array of grey values in
[0, 255] (``S`` a power of two), tileable (it wraps around at its borders
without a seam) unless made from a user image, with an optional alpha mask
(1 = opaque) for cut-out billboards such as tree crowns. The generators mix
octaves of smoothed noise (1/f^beta spectra, made periodic by construction in
the Fourier domain) with sharp structures (blobs, planks, bricks, windows,
posters) so that a moving event camera sees both fine texture and strong
edges. All generators are deterministic functions of their ``seed``.

:class:`TextureAtlas` stacks the textures with their mip pyramids (2x2 box
filter) into one flat float32 buffer for the renderer's trilinear lookups.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

__all__ = [
    "Texture", "TextureAtlas", "fractal_noise", "make_texture", "texture_from_image",
    "TEXTURE_KINDS", "night_version",
]


@dataclass(frozen=True, eq=False)
class Texture:
    """A square grey texture.

    Attributes
    ----------
    values : ndarray, shape (S, S), float32
        Grey values in [0, 255]; row index = texel y.
    alpha : ndarray, shape (S, S), bool, or None
        Opaque texels of a cut-out texture; ``None`` when fully opaque.
    name : str
    windows : ndarray, shape (S, S), bool, or None
        Texels that may glow at night (window panes), see :func:`night_version`.
    """

    values: np.ndarray
    alpha: np.ndarray | None = None
    name: str = ""
    windows: np.ndarray | None = None

    def __post_init__(self) -> None:
        values = np.asarray(self.values, dtype=np.float32)
        size = values.shape[0] if values.ndim == 2 else 0
        if values.ndim != 2 or values.shape[1] != size or size < 4 or size & (size - 1):
            raise ValueError(f"values must be a square (S, S) array, S a power of two >= 4; got {values.shape}")
        if not np.isfinite(values).all() or values.min() < 0 or values.max() > 255:
            raise ValueError("values must be finite grey levels in [0, 255]")
        object.__setattr__(self, "values", np.ascontiguousarray(values))
        if self.alpha is not None:
            alpha = np.asarray(self.alpha, dtype=bool)
            if alpha.shape != values.shape:
                raise ValueError(f"alpha must have shape {values.shape}, got {alpha.shape}")
            object.__setattr__(self, "alpha", alpha)
        if self.windows is not None and np.shape(self.windows) != values.shape:
            raise ValueError(f"windows must have shape {values.shape}, got {np.shape(self.windows)}")

    @property
    def size(self) -> int:
        return int(self.values.shape[0])


# -- building blocks ----------------------------------------------------------------------
def fractal_noise(size: int, rng: np.random.Generator, *, beta: float = 2.0, min_period: float = 2.0) -> np.ndarray:
    """Periodic noise (size, size) float64 with power spectrum ~ 1/f^beta, scaled to [0, 1].

    Made in the Fourier domain, so it tiles seamlessly. ``beta = 2`` looks
    like natural images (all octaves equally strong); larger is smoother.
    Frequencies above ``1/min_period`` cycles per texel are removed.
    """
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    amplitude = np.where(f > 0, np.maximum(f, 1.0 / size) ** (-beta / 2.0), 0.0)
    amplitude[f > 1.0 / min_period] = 0.0
    spectrum = amplitude * (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape))
    noise = np.fft.irfft2(spectrum, s=(size, size))
    return _normalize(noise)


def _normalize(x: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(x, [0.5, 99.5])
    return np.clip((x - lo) / max(hi - lo, 1e-12), 0.0, 1.0)


def _wrap_draw(size: int, draw: Callable[[np.ndarray, int, int], None], canvas: np.ndarray) -> None:
    """Call ``draw(canvas, dx, dy)`` for the 9 periodic copies so shapes wrap around."""
    for dy in (-size, 0, size):
        for dx in (-size, 0, size):
            draw(canvas, dx, dy)


def _blobs(size: int, rng: np.random.Generator, count: int, radius: tuple[float, float],
           levels: tuple[float, float] = (0.0, 1.0), canvas: np.ndarray | None = None) -> np.ndarray:
    """Random filled ellipses with sharp (anti-aliased) edges on a periodic canvas in [0, 1]."""
    out = np.zeros((size, size), np.float32) if canvas is None else canvas
    shift = 4  # sub-pixel precision of cv2 drawing
    for _ in range(count):
        cx, cy = rng.uniform(0, size, 2)
        ax = rng.uniform(radius[0], max(radius))
        ay = ax * rng.uniform(0.4, 1.0)
        angle = rng.uniform(0, 180)
        level = float(rng.uniform(*levels))

        def draw(canvas: np.ndarray, dx: int, dy: int) -> None:
            cv2.ellipse(
                canvas, (int((cx + dx) * 16), int((cy + dy) * 16)), (int(ax * 16), int(ay * 16)),
                angle, 0, 360, level, -1, cv2.LINE_AA, shift,
            )

        _wrap_draw(size, draw, out)
    return out


def _rectangle(canvas: np.ndarray, x0: float, y0: float, x1: float, y1: float, level: float) -> None:
    size = canvas.shape[0]

    def draw(c: np.ndarray, dx: int, dy: int) -> None:
        cv2.rectangle(c, (int(x0 + dx), int(y0 + dy)), (int(x1 + dx) - 1, int(y1 + dy) - 1), level, -1)

    _wrap_draw(size, draw, canvas)


def _to_grey(x: np.ndarray, low: float, high: float) -> np.ndarray:
    return (low + (high - low) * np.clip(x, 0.0, 1.0)).astype(np.float32)


# -- texture kinds ------------------------------------------------------------------------
def _plaster(size: int, rng: np.random.Generator) -> Texture:
    """Painted wall: soft stains plus posters, frames and switches (sharp edges)."""
    base = 0.55 + 0.25 * fractal_noise(size, rng, beta=2.6) + 0.08 * fractal_noise(size, rng, beta=1.2)
    for _ in range(rng.integers(3, 7)):
        w, h = rng.uniform(0.08, 0.3, 2) * size
        x0, y0 = rng.uniform(0, size, 2)
        inner = fractal_noise(size, rng, beta=1.8)
        _rectangle(base, x0, y0, x0 + w, y0 + h, float(rng.uniform(0.05, 0.95)))
        patch = np.zeros_like(base)
        _rectangle(patch, x0 + 3, y0 + 3, x0 + w - 3, y0 + h - 3, 1.0)
        base = np.where(patch > 0, 0.15 + 0.8 * inner, base)
    _blobs(size, rng, int(rng.integers(10, 30)), (2, size / 24), (0.0, 1.0), base)
    return Texture(_to_grey(base, 20, 235), name="plaster")


def _wood(size: int, rng: np.random.Generator) -> Texture:
    """Floor of planks: stretched grain noise per plank and dark seams."""
    grain = fractal_noise(size, rng, beta=2.2)
    grain = cv2.resize(grain[:, : size // 8], (size, size), interpolation=cv2.INTER_LINEAR)
    planks = 8
    height = size // planks
    out = np.empty((size, size))
    for k in range(planks):
        shift = int(rng.integers(0, size))
        rows = slice(k * height, (k + 1) * height)
        out[rows] = np.roll(grain[rows], shift, axis=1) * 0.6 + rng.uniform(0.1, 0.4)
        out[k * height: k * height + 2] = 0.05
        joint = int(rng.integers(0, size))
        out[rows, joint: joint + 2] = 0.05
    return Texture(_to_grey(out, 15, 230), name="wood")


def _mat(size: int, rng: np.random.Generator) -> Texture:
    """Foam floor mats (as in MVSEC's flying arena): tiles of speckled noise with seams."""
    speckle = fractal_noise(size, rng, beta=1.0)
    tiles = 4
    step = size // tiles
    out = 0.35 + 0.4 * speckle
    for i in range(tiles):
        for j in range(tiles):
            out[i * step: (i + 1) * step, j * step: (j + 1) * step] += rng.uniform(-0.25, 0.25)
    out[::step] = 0.05
    out[:, ::step] = 0.05
    _blobs(size, rng, 12, (3, size / 20), (0.0, 1.0), out)
    return Texture(_to_grey(out, 10, 240), name="mat")


def _asphalt(size: int, rng: np.random.Generator) -> Texture:
    """Road: fine aggregate noise, patches, cracks; lane markings along the texture's x."""
    out = 0.35 + 0.25 * fractal_noise(size, rng, beta=1.0) + 0.2 * fractal_noise(size, rng, beta=2.8)
    _blobs(size, rng, 10, (size / 30, size / 8), (0.15, 0.55), out)
    for _ in range(8):  # cracks
        points = np.cumsum(rng.normal(0, 6, (12, 2)), axis=0) + rng.uniform(0, size, 2)
        cv2.polylines(out, [(points * 16).astype(np.int32)], False, 0.05, 1, cv2.LINE_AA, 4)
    # Dashed centre line and solid edge lines (texture y = across the road).
    mid, edge = size // 2, size // 16
    for x0 in range(0, size, size // 4):
        _rectangle(out, x0, mid - 3, x0 + size // 8, mid + 3, 0.95)
    _rectangle(out, 0, edge, size, edge + 5, 0.9)
    _rectangle(out, 0, size - edge - 5, size, size - edge, 0.9)
    return Texture(_to_grey(out, 10, 245), name="asphalt")


def _facade(size: int, rng: np.random.Generator) -> Texture:
    """Building front: brick/plaster noise and a grid of dark windows with frames."""
    wall = 0.45 + 0.3 * fractal_noise(size, rng, beta=2.4) + 0.1 * fractal_noise(size, rng, beta=0.8)
    rows = int(rng.integers(3, 6))
    cols = int(rng.integers(3, 6))
    cell_w, cell_h = size / cols, size / rows
    wall += rng.uniform(-0.15, 0.15)
    glass = fractal_noise(size, rng, beta=3.0)
    windows = np.zeros((size, size), bool)
    for i in range(rows):
        for j in range(cols):
            x0 = j * cell_w + 0.25 * cell_w
            y0 = i * cell_h + 0.2 * cell_h
            x1, y1 = x0 + 0.5 * cell_w, y0 + 0.55 * cell_h
            _rectangle(wall, x0 - 3, y0 - 3, x1 + 3, y1 + 3, 0.95)  # frame
            sub = wall[int(y0): int(y1), int(x0): int(x1)]
            sub[:] = 0.05 + 0.25 * glass[int(y0): int(y1), int(x0): int(x1)]
            if rng.random() < 0.5:  # a curtain or a reflection
                sub[:, : sub.shape[1] // 3] += 0.35
            sub[sub.shape[0] // 2 - 1: sub.shape[0] // 2 + 1] = 0.9  # mullion
            windows[int(y0): int(y1), int(x0): int(x1)] = True
    return Texture(_to_grey(wall, 10, 240), name="facade", windows=windows)


def _foliage(size: int, rng: np.random.Generator) -> Texture:
    """Tree crown: leaves (many small blobs) on a cut-out of merged discs."""
    alpha = np.zeros((size, size), np.float32)
    centre = np.array([size / 2, size / 2])
    for _ in range(14):
        c = centre + rng.normal(0, size / 9, 2)
        r = rng.uniform(size / 8, size / 4.5)
        cv2.circle(alpha, (int(c[0]), int(c[1])), int(r), 1.0, -1, cv2.LINE_AA)
    edge = fractal_noise(size, rng, beta=1.6)
    alpha = (alpha * (0.6 + 0.6 * edge)) > 0.55
    leaves = 0.25 + 0.3 * fractal_noise(size, rng, beta=2.5)
    _blobs(size, rng, 900, (1.5, size / 60), (0.0, 0.9), leaves)
    shade = np.linspace(0.9, 0.55, size)[:, None]  # darker underneath
    return Texture(_to_grey(leaves * shade, 5, 220), alpha=alpha, name="foliage")


def _bark(size: int, rng: np.random.Generator) -> Texture:
    """Tree trunk or pole: vertical streaks."""
    streaks = fractal_noise(size, rng, beta=2.0)
    streaks = cv2.resize(streaks[: size // 8], (size, size), interpolation=cv2.INTER_LINEAR)
    out = 0.2 + 0.5 * streaks + 0.15 * fractal_noise(size, rng, beta=1.0)
    return Texture(_to_grey(out, 10, 200), name="bark")


def _ground(size: int, rng: np.random.Generator) -> Texture:
    """Natural ground (grass, dirt, pebbles, twigs) for terrain and lawns."""
    out = 0.3 + 0.35 * fractal_noise(size, rng, beta=2.2) + 0.25 * fractal_noise(size, rng, beta=0.8)
    pebbles = _blobs(size, rng, 700, (0.8, size / 110), (0.0, 1.0))
    mask = _blobs(size, rng, 700, (0.8, size / 110), (1.0, 1.0))  # same count, independent shapes
    out = np.where(mask > 0.5, 0.5 * out + 0.5 * pebbles, out)
    for _ in range(40):  # twigs and cracks
        points = np.cumsum(rng.normal(0, 3, (6, 2)), axis=0) + rng.uniform(0, size, 2)
        cv2.polylines(out, [(points * 16).astype(np.int32)], False, float(rng.uniform(0, 0.2)), 1, cv2.LINE_AA, 4)
    return Texture(_to_grey(out, 10, 235), name="ground")


def _rock(size: int, rng: np.random.Generator) -> Texture:
    out = 0.35 + 0.45 * fractal_noise(size, rng, beta=2.0)
    for _ in range(10):
        points = np.cumsum(rng.normal(0, 10, (10, 2)), axis=0) + rng.uniform(0, size, 2)
        cv2.polylines(out, [(points * 16).astype(np.int32)], False, 0.05, 2, cv2.LINE_AA, 4)
    return Texture(_to_grey(out, 15, 235), name="rock")


def _car(size: int, rng: np.random.Generator) -> Texture:
    """Car side: a uniform paint with dark windows, wheels and a reflection line."""
    paint = float(rng.uniform(0.15, 0.9))
    out = paint + 0.06 * fractal_noise(size, rng, beta=2.5)
    _rectangle(out, size * 0.15, size * 0.1, size * 0.85, size * 0.42, 0.08)
    _rectangle(out, size * 0.48, size * 0.1, size * 0.52, size * 0.42, paint)
    out[int(size * 0.55): int(size * 0.57)] = min(paint + 0.3, 1.0)
    for cx in (0.22, 0.78):
        cv2.circle(out, (int(cx * size), int(0.88 * size)), int(0.13 * size), 0.03, -1, cv2.LINE_AA)
        cv2.circle(out, (int(cx * size), int(0.88 * size)), int(0.06 * size), 0.6, -1, cv2.LINE_AA)
    return Texture(_to_grey(out, 5, 245), name="car")


def _poster(size: int, rng: np.random.Generator) -> Texture:
    """A busy picture: many shapes of all sizes and grey levels (like ECD's posters)."""
    out = fractal_noise(size, rng, beta=1.5)
    _blobs(size, rng, 60, (size / 60, size / 6), (0.0, 1.0), out)
    for _ in range(25):
        x0, y0 = rng.uniform(0, size, 2)
        w, h = rng.uniform(max(size / 40, 1.0), max(size / 6, 2.0), 2)
        _rectangle(out, x0, y0, x0 + w, y0 + h, float(rng.uniform(0, 1)))
    return Texture(_to_grey(out, 5, 250), name="poster")


TEXTURE_KINDS: dict[str, Callable[[int, np.random.Generator], Texture]] = {
    "plaster": _plaster, "wood": _wood, "mat": _mat, "asphalt": _asphalt, "facade": _facade,
    "foliage": _foliage, "bark": _bark, "ground": _ground, "rock": _rock, "car": _car,
    "poster": _poster,
}


def make_texture(kind: str, seed: int = 0, size: int = 512) -> Texture:
    """A procedural texture of ``kind`` (one of :data:`TEXTURE_KINDS`), deterministic in ``seed``.

    Examples
    --------
    >>> make_texture("poster", seed=1, size=64).values.shape
    (64, 64)
    """
    if kind not in TEXTURE_KINDS:
        raise ValueError(f"kind must be one of {sorted(TEXTURE_KINDS)}, got {kind!r}")
    if not isinstance(size, (int, np.integer)) or size < 16 or size & (size - 1):
        raise ValueError(f"size must be a power of two >= 16, got {size!r}")
    rng = np.random.default_rng([int(seed), sorted(TEXTURE_KINDS).index(kind)])
    return TEXTURE_KINDS[kind](int(size), rng)


def night_version(texture: Texture, rng: np.random.Generator, *, gain: float = 0.18,
                  lit_fraction: float = 0.0) -> Texture:
    """A dim, low-contrast copy of ``texture`` (night time), optionally with lit windows.

    Grey values become ``255 * (0.015 + gain * (I/255)^1.3)``; when
    ``lit_fraction > 0`` and the texture has ``windows``, that fraction of its
    window panes (connected regions) glows at about 150-230 grey levels.
    """
    x = texture.values / 255.0
    out = 0.015 + gain * x**1.3
    if lit_fraction > 0 and texture.windows is not None:
        count, labels = cv2.connectedComponents(texture.windows.astype(np.uint8), connectivity=4)
        brightness = rng.uniform(0.55, 0.85, count)
        lit = (rng.random(count) < lit_fraction) & (np.arange(count) > 0)
        glow = lit[labels]
        out = np.where(glow, brightness[labels] + 0.12 * x, out)
    return Texture(_to_grey(out, 0, 255), alpha=texture.alpha, name=texture.name + "_night")


def texture_from_image(image: np.ndarray, size: int = 512, *, alpha: np.ndarray | None = None) -> Texture:
    """A texture from a user image (H, W) grey or (H, W, 3) BGR, uint8 or float in [0, 255].

    The image is resized to ``size`` x ``size`` (area interpolation); it does
    not tile seamlessly, so map it once onto a rectangle.
    """
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image.astype(np.float32), cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or min(image.shape) < 2:
        raise ValueError(f"image must have shape (H, W) or (H, W, 3), got {image.shape}")
    if not isinstance(size, (int, np.integer)) or size < 4 or size & (size - 1):
        raise ValueError(f"size must be a power of two >= 4, got {size!r}")
    values = cv2.resize(image.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    if alpha is not None:
        alpha = cv2.resize(np.asarray(alpha, np.float32), (size, size), interpolation=cv2.INTER_LINEAR) > 0.5
    return Texture(np.clip(values, 0, 255), alpha=alpha, name="image")


# -- atlas ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class TextureAtlas:
    """All textures of a scene with their mip pyramids, packed into one image.

    Each texture owns a cell of the atlas holding its levels ``l = 0 .. levels-1``
    (side ``S_l = S >> l``, a 2x2 box filter from one level to the next, down
    to 4 texels): level 0 at the cell's left, the smaller levels stacked to its
    right. Every level carries one extra wrapped row and column so that a
    bilinear lookup at ``origin + x`` with ``0 <= x < S_l`` (after reducing the
    texel coordinate modulo ``S_l``) never reads outside its level: lookups
    wrap without seams. The renderer samples it with ``cv2.remap``.

    Attributes
    ----------
    size : int
        Side ``S`` of every level-0 texture (textures of other sizes are resized).
    levels : int
    image : ndarray, shape (Ha, Wa), float32
        The packed atlas (grey levels); both sides below 32767 (OpenCV's limit).
    origins : ndarray, shape (n, levels, 2), float32
        Atlas column and row of texel (0, 0) of level ``l`` of texture ``k``.
    alpha : ndarray, shape (n*S*S,), bool
        Level-0 opacity, row-major per texture (all True for opaque textures).
    count : int
    """

    size: int
    levels: int
    image: np.ndarray
    origins: np.ndarray
    alpha: np.ndarray
    count: int

    @classmethod
    def build(cls, textures: list[Texture], size: int = 512) -> "TextureAtlas":
        """Resize ``textures`` to ``size`` (a power of two) and pack their mip pyramids."""
        if not textures:
            raise ValueError("textures must not be empty")
        if not isinstance(size, (int, np.integer)) or size < 4 or size & (size - 1):
            raise ValueError(f"size must be a power of two >= 4, got {size!r}")
        size = int(size)
        levels = int(np.log2(size)) - 1  # down to 4 texels
        sides = [size >> level for level in range(levels)]
        level_x = [0] + [size + 1] * (levels - 1)
        level_y = [0] + list(np.cumsum([0] + [side + 1 for side in sides[1:-1]]))
        cell_w = size + 1 + (sides[1] + 1 if levels > 1 else 0)
        cell_h = max(size + 1, sum(side + 1 for side in sides[1:]))
        cols = int(np.ceil(np.sqrt(len(textures))))
        rows = -(-len(textures) // cols)
        if cols * cell_w >= 32767 or rows * cell_h >= 32767:
            raise ValueError(f"{len(textures)} textures of {size} texels do not fit into one atlas")
        image = np.zeros((rows * cell_h, cols * cell_w), np.float32)
        origins = np.zeros((len(textures), levels, 2), np.float32)
        alphas = []
        for k, texture in enumerate(textures):
            if not isinstance(texture, Texture):
                raise TypeError(f"textures must be Texture objects, got {type(texture).__name__}")
            values = texture.values
            alpha = texture.alpha if texture.alpha is not None else np.ones(values.shape, bool)
            if texture.size != size:
                interp = cv2.INTER_AREA if texture.size > size else cv2.INTER_LINEAR
                values = cv2.resize(values, (size, size), interpolation=interp)
                alpha = cv2.resize(alpha.astype(np.float32), (size, size), interpolation=cv2.INTER_LINEAR) > 0.5
            alphas.append(alpha)
            x0, y0 = (k % cols) * cell_w, (k // cols) * cell_h
            level = values.astype(np.float32)
            for l in range(levels):
                if l:
                    level = 0.25 * (level[::2, ::2] + level[1::2, ::2] + level[::2, 1::2] + level[1::2, 1::2])
                x, y = x0 + level_x[l], y0 + level_y[l]
                image[y: y + sides[l] + 1, x: x + sides[l] + 1] = np.pad(level, ((0, 1), (0, 1)), mode="wrap")
                origins[k, l] = (x, y)
        return cls(size, levels, image, origins, np.stack(alphas).ravel(), len(textures))
