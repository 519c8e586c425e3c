"""The fast voting of EMVS: one splat per group of packets, one image addition per plane.

Events of consecutive packets whose camera centres stay close share one
affine transfer (:class:`cmax.emvs.dsi.PlaneTransfer`). :func:`gather_votes`
splats them once (bilinear) on the base plane, on grids shifted by multiples
of ``1/S`` px. A plane whose transfer is a translation (camera moving
parallel to the image plane) then receives the grid of its sub-pixel phase
added at an integer offset (the exact bilinear votes, offset rounded to
``1/S`` px), so the cost per plane is one image addition whatever the number
of events. Scaled planes (motion along the optical axis) receive the splat
resampled by ``cv2.warpAffine`` (times ``1 / a_i**2``, one vote per event and
plane).

The image additions are the bulk of the work. :class:`ShiftedAdditions`
collects them over several groups (the shifted images in one buffer) and
:func:`add_shifted` runs them in one compiled pass, row band by row band, so
that a band of every plane stays in the cache while all the groups' images
are added to it; every DSI cell still receives its additions in group order,
so the sums are those of adding group after group (float32, bit for bit).
"""
from __future__ import annotations

import cv2
import numpy as np

from cmax._jit import kernel
from cmax.emvs.dsi import PlaneTransfer, _splat_layers, bilinear_splat, splat_votes

__all__ = ["gather_votes", "ShiftedAdditions", "add_shifted"]

#: A gather canvas larger than this many reference images falls back to splatting.
_MAX_CANVAS_IMAGES = 16
#: Shifted images are splatted directly (not box-filtered from a fine grid) below this many
#: event-shifts per fine-grid cell.
_DIRECT_SPLATS_PER_CELL = 4
#: Floats of shifted images that :class:`ShiftedAdditions` holds before it adds them (32 MiB).
_POOL_FLOATS = 1 << 23
#: Bytes of DSI rows (all planes) that one band of :func:`add_shifted` covers.
_BAND_BYTES = 1 << 19


@kernel
def _canvas_box(positions, scales, offsets, valid, width, height, box):
    """``box`` (4,) float64 = ``(x0, y0, x1, y1)`` of :func:`_canvas` (``x1 < x0`` or ``y1 < y0``: empty)."""
    reach_lo_x, reach_lo_y, reach_hi_x, reach_hi_y = np.inf, np.inf, -np.inf, -np.inf
    for i in range(scales.shape[0]):
        if valid[i]:
            a = scales[i]
            reach_lo_x = min(reach_lo_x, (-1.0 - offsets[i, 0]) / a)
            reach_lo_y = min(reach_lo_y, (-1.0 - offsets[i, 1]) / a)
            reach_hi_x = max(reach_hi_x, (width - offsets[i, 0]) / a)
            reach_hi_y = max(reach_hi_y, (height - offsets[i, 1]) / a)
    lo_x, lo_y, hi_x, hi_y = positions[0, 0], positions[0, 1], positions[0, 0], positions[0, 1]
    for i in range(1, positions.shape[0]):
        lo_x, hi_x = min(lo_x, positions[i, 0]), max(hi_x, positions[i, 0])
        lo_y, hi_y = min(lo_y, positions[i, 1]), max(hi_y, positions[i, 1])
    box[0] = max(np.floor(lo_x), np.floor(reach_lo_x))
    box[1] = max(np.floor(lo_y), np.floor(reach_lo_y))
    box[2] = min(np.floor(hi_x) + 1.0, np.ceil(reach_hi_x))
    box[3] = min(np.floor(hi_y) + 1.0, np.ceil(reach_hi_y))


def _canvas(positions: np.ndarray, transfer: PlaneTransfer, width: int, height: int
            ) -> tuple[int, int, int, int] | None:
    """Base-plane rectangle ``(x0, y0, x1, y1)`` (inclusive) holding every vote that reaches the image.

    The positions' bounding box, cut to the base-plane points that some valid
    plane maps into ``[-1, W] x [-1, H]`` (the reach of a bilinear gather);
    ``None`` when they do not meet. ``positions`` (N, 2) float64 [px], N >= 1.
    """
    box = np.empty(4)
    _canvas_box(positions, transfer.scales, transfer.offsets, transfer.valid, float(width), float(height), box)
    if box[2] < box[0] or box[3] < box[1]:
        return None
    return int(box[0]), int(box[1]), int(box[2]), int(box[3])


def _phase_images(positions: np.ndarray, x0: int, y0: int, width: int, height: int, subpixel: int,
                  x_phases: np.ndarray, y_phases: np.ndarray, out: np.ndarray) -> None:
    """Bilinear votes on sub-pixel-shifted grids, written to ``out`` (len(y_phases), len(x_phases), height, width).

    ``out`` is float32. Layer ``[m, n]`` holds the cells centred at base-plane pixels
    ``(x0 + k + x_phases[n] / S, y0 + l + y_phases[m] / S)``: exactly the
    bilinear splat of the positions (N, 2) shifted by ``-(x_phases[n], y_phases[m]) / S``.
    Along an axis with several phases the positions are splatted on a grid
    ``S`` times finer (sub-cell ``J`` centred at ``x0 + J / S``) and two box
    filters of ``S`` sub-cells make the triangle of half-width ``S`` sub-cells,
    whose linear interpolation of that splat is the 1-pixel bilinear tent;
    along an axis with one phase the shifted positions are splatted directly.
    """
    S = subpixel
    sx = S if len(x_phases) > 1 else 1
    sy = S if len(y_phases) > 1 else 1
    layers = len(x_phases) * len(y_phases)
    if len(positions) * layers <= _DIRECT_SPLATS_PER_CELL * sx * sy * width * height:
        # Few events for the fine grid: splat each needed shift directly (one compiled pass).
        shift_x = np.tile(x_phases / S, len(y_phases))
        shift_y = np.repeat(y_phases / S, len(x_phases))
        _splat_shifted(np.ascontiguousarray(positions, dtype=np.float64), float(x0), float(y0), shift_x, shift_y,
                       out.reshape(layers, height, width), np.empty((1, height, width)))
        return
    u = (positions[:, 0] - x0 - (x_phases[0] / S if sx == 1 else 0.0)) * sx
    v = (positions[:, 1] - y0 - (y_phases[0] / S if sy == 1 else 0.0)) * sy
    fine = bilinear_splat(u[None], v[None], None, sx * width, sy * height)[0].astype(np.float32)
    if sx == sy == 1:
        out[0, 0] = fine
        return
    once = cv2.boxFilter(fine, -1, (sx, sy), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    tent = cv2.boxFilter(once, -1, (sx, sy), anchor=(sx - 1, sy - 1), normalize=True,
                         borderType=cv2.BORDER_CONSTANT)
    # tent[sy l + j, sx k + i] is cell (l, k) of the grid shifted by (i, j) / S.
    grid = tent.reshape(height, sy, width, sx)
    rows = y_phases if sy > 1 else np.zeros(1, np.int64)
    cols = x_phases if sx > 1 else np.zeros(1, np.int64)
    out[...] = grid[:, rows][:, :, :, cols].transpose(1, 3, 0, 2)


@kernel
def _splat_shifted(positions, x0, y0, shift_x, shift_y, out, scratch):
    """Layer ``k`` of ``out`` (m, H, W) float32 = the bilinear splat of ``positions`` (N, 2) [px]
    at ``(x - x0 - shift_x[k], y - y0 - shift_y[k])``, summed in float64 (``scratch`` (1, H, W)).

    The arithmetic of :func:`cmax.emvs.dsi.bilinear_splat` with unit weights, cast to float32.
    """
    n = positions.shape[0]
    u = np.empty((1, n))
    v = np.empty((1, n))
    no_weights = np.zeros((0, 0))
    sums = scratch[0]
    sums[:] = 0.0
    for k in range(out.shape[0]):
        for i in range(n):
            u[0, i] = positions[i, 0] - x0 - shift_x[k]
            v[0, i] = positions[i, 1] - y0 - shift_y[k]
        _splat_layers(u, v, no_weights, scratch)
        layer = out[k]
        for y in range(sums.shape[0]):  # cast, and zero the sums for the next layer, in one pass
            row, cast = sums[y], layer[y]
            for x in range(sums.shape[1]):
                cast[x] = row[x]
                row[x] = 0.0


@kernel
def _add_shifted(dsi, pool, layer_start, layer_height, layer_width, plane, layer, qx, qy, band):
    """``dsi[plane[a], p] += image layer[a] at p + (qx[a], qy[a])`` for every addition ``a``, in order.

    ``pool`` (float32, flat) holds the images: layer ``l`` is ``layer_height[l]`` x
    ``layer_width[l]`` from ``layer_start[l]``. Row bands of ``band`` rows outermost.
    """
    height, width = dsi.shape[1], dsi.shape[2]
    for r0 in range(0, height, band):
        r1 = min(height, r0 + band)
        for a in range(plane.shape[0]):
            k = layer[a]
            dx, dy, image_w = qx[a], qy[a], layer_width[k]
            lo_x, hi_x = max(0, -dx), min(width, image_w - dx)
            lo_y, hi_y = max(r0, -dy), min(r1, layer_height[k] - dy)
            if hi_x <= lo_x or hi_y <= lo_y:
                continue
            target = dsi[plane[a]]
            count = hi_x - lo_x
            for y in range(lo_y, hi_y):
                row = target[y, lo_x:hi_x]
                start = layer_start[k] + (y + dy) * image_w + dx + lo_x
                source = pool[start: start + count]
                for x in range(count):
                    row[x] += source[x]


def add_shifted(dsi: np.ndarray, pool: np.ndarray, layer_start: np.ndarray, layer_shape: np.ndarray,
                plane: np.ndarray, layer: np.ndarray, offset: np.ndarray) -> None:
    """Add images at integer offsets to planes of the DSI, in place (one compiled pass).

    Parameters
    ----------
    dsi : ndarray, shape (n_planes, H, W), float32, C-contiguous
    pool : ndarray, shape (F,), float32
        The images, flattened one after the other.
    layer_start : ndarray, shape (L,), int64
        Where image ``l`` starts in ``pool``.
    layer_shape : ndarray, shape (L, 2), int64
        ``(height, width)`` of image ``l``.
    plane, layer : ndarray, shape (A,), int64
        Addition ``a`` adds image ``layer[a]`` to plane ``plane[a]``.
    offset : ndarray, shape (A, 2), int64
        ``(qx, qy)``: ``dsi[plane, y, x] += image[y + qy, x + qx]`` over the overlap.

    Additions to the same cell happen in the order of ``a``: the result is that of
    adding one image after the other (float32).

    Examples
    --------
    One 2 x 3 image added to plane 1, read one column to the right (``qx = 1``):

    >>> import numpy as np
    >>> dsi = np.zeros((2, 2, 3), np.float32)
    >>> pool = np.arange(1, 7, dtype=np.float32)  # the image [[1, 2, 3], [4, 5, 6]]
    >>> add_shifted(dsi, pool, np.array([0]), np.array([[2, 3]]), np.array([1]), np.array([0]), np.array([[1, 0]]))
    >>> dsi[1].tolist()
    [[2.0, 3.0, 0.0], [5.0, 6.0, 0.0]]
    """
    if dsi.dtype != np.float32 or not dsi.flags.c_contiguous or dsi.ndim != 3:
        raise ValueError("dsi must be a C-contiguous float32 array (n_planes, H, W)")
    if pool.dtype != np.float32 or pool.ndim != 1 or not pool.flags.c_contiguous:
        raise ValueError("pool must be a contiguous 1-D float32 array")
    shape = np.asarray(layer_shape, dtype=np.int64).reshape(-1, 2)
    layer_start = np.asarray(layer_start, dtype=np.int64)
    plane, layer = np.asarray(plane, dtype=np.int64), np.asarray(layer, dtype=np.int64)
    if len(layer_start) != len(shape) or np.any(shape < 1) or np.any(layer_start < 0) or np.any(
            layer_start + shape[:, 0] * shape[:, 1] > len(pool)):
        raise ValueError(f"{len(layer_start)} images of {len(shape)} shapes must lie inside the pool of {len(pool)}")
    if np.any((layer < 0) | (layer >= len(shape))) or np.any((plane < 0) | (plane >= dsi.shape[0])):
        raise ValueError("additions must name images of the pool and planes of the DSI")
    if not len(plane):
        return
    band = max(1, _BAND_BYTES // (dsi.shape[0] * dsi.shape[2] * 4))
    # Plane by plane (a band of one plane stays in L1 while its additions run), in order within a plane.
    order = np.argsort(plane, kind="stable")
    offset = np.asarray(offset, dtype=np.int64)[order]
    _add_shifted(dsi, pool, np.ascontiguousarray(layer_start), shape[:, 0].copy(), shape[:, 1].copy(),
                 plane[order], layer[order], offset[:, 0].copy(), offset[:, 1].copy(), band)


class ShiftedAdditions:
    """Image additions of several groups, held in one buffer and added to the DSI in one pass.

    :meth:`images` hands out room for a group's shifted images, :meth:`add`
    records which plane receives which image at which offset, :meth:`flush`
    performs every recorded addition (:func:`add_shifted`) and frees the
    buffer; it runs by itself when the buffer is full. Call :meth:`flush`
    before anything else writes to the planes, and at the end.
    """

    def __init__(self, dsi: np.ndarray, pool_floats: int | None = None) -> None:
        self.dsi = dsi
        self._pool = np.empty(0, np.float32)
        self._pool_floats = _POOL_FLOATS if pool_floats is None else int(pool_floats)
        self._used = 0
        self._starts: list[np.ndarray] = []
        self._shapes: list[tuple[int, int, int]] = []
        self._plane: list[np.ndarray] = []
        self._layer: list[np.ndarray] = []
        self._offset: list[np.ndarray] = []
        self._layers = 0

    def images(self, layers: int, height: int, width: int) -> np.ndarray:
        """Room (layers, height, width) float32 for one group's images (contents undefined)."""
        size = layers * height * width
        if self._used + size > len(self._pool):
            self.flush()
            if size > len(self._pool):
                self._pool = np.empty(max(size, self._pool_floats), np.float32)
        view = self._pool[self._used: self._used + size].reshape(layers, height, width)
        self._starts.append(self._used + np.arange(layers, dtype=np.int64) * (height * width))
        self._shapes.append((layers, height, width))
        self._used += size
        return view

    def add(self, plane: np.ndarray, layer: np.ndarray, offset: np.ndarray) -> None:
        """Record additions of the images of the last :meth:`images` call: image ``layer[a]`` to
        plane ``plane[a]`` at ``offset[a] = (qx, qy)`` (see :func:`add_shifted`)."""
        self._plane.append(np.asarray(plane, np.int64))
        self._layer.append(np.asarray(layer, np.int64) + self._layers)
        self._offset.append(np.asarray(offset, np.int64).reshape(-1, 2))
        self._layers += self._shapes[-1][0]

    def flush(self) -> None:
        """Perform every recorded addition and empty the buffer."""
        if self._plane:
            shapes = np.concatenate([np.tile([h, w], (n, 1)) for n, h, w in self._shapes])
            add_shifted(self.dsi, self._pool, np.concatenate(self._starts), shapes, np.concatenate(self._plane),
                        np.concatenate(self._layer), np.concatenate(self._offset))
        self._used, self._layers = 0, 0
        self._starts, self._shapes, self._plane, self._layer, self._offset = [], [], [], [], []


def _warp_add(target: np.ndarray, image: np.ndarray, scale: float, offset: np.ndarray, x0: int, y0: int) -> None:
    """``target[p] += image((p - offset) / scale - (x0, y0)) / scale**2`` (bilinear gather, ``cv2.warpAffine``)."""
    height, width = target.shape
    canvas_h, canvas_w = image.shape
    a = scale
    bx, by = float(offset[0]), float(offset[1])
    x1, y1 = x0 + canvas_w - 1, y0 + canvas_h - 1
    # Destination rectangle that the canvas can reach.
    rx0, ry0 = max(0, int(np.floor(a * (x0 - 1) + bx))), max(0, int(np.floor(a * (y0 - 1) + by)))
    rx1 = min(width, int(np.ceil(a * (x1 + 1) + bx)) + 1)
    ry1 = min(height, int(np.ceil(a * (y1 + 1) + by)) + 1)
    if rx1 <= rx0 or ry1 <= ry0:
        return
    # Destination pixel p (relative to the rectangle) reads canvas ((p + r0 - b) / a - x0).
    matrix = np.array([[1.0 / a, 0.0, (rx0 - bx) / a - x0], [0.0, 1.0 / a, (ry0 - by) / a - y0]])
    warped = cv2.warpAffine(image, matrix, (rx1 - rx0, ry1 - ry0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    region = target[ry0:ry1, rx0:rx1]
    cv2.scaleAdd(warped, 1.0 / (a * a), region, dst=region)


def gather_votes(dsi: np.ndarray, positions: np.ndarray, transfer: PlaneTransfer, *, subpixel: int = 4,
                 pending: ShiftedAdditions | None = None) -> None:
    """Add the votes of base-plane positions (N, 2) to ``dsi`` by splatting once and shifting per plane.

    A plane whose transfer is a translation to within ``1/(2S)`` px over the
    splat (``|a_i - 1|`` times its half-diagonal; ``S = subpixel``) receives
    the bilinear splat of the positions on a grid shifted by a multiple of
    ``1/S`` px, added at an integer offset: the exact bilinear votes with
    the plane's offset rounded to ``1/S`` px. The grids are made once per call
    (:func:`_phase_images`), only for the sub-pixel phases that some plane
    needs. Other planes (a camera moving along its axis) receive the
    unshifted splat resampled by ``cv2.warpAffine`` (bilinear gather at 1/32 px,
    times ``1 / a_i**2`` so that every event keeps one vote per plane). Falls
    back to :func:`cmax.emvs.dsi.splat_votes` when the events spread over a
    base-plane area of more than 16 reference images.

    ``dsi`` (n_planes, H, W) float32 is changed in place. With ``pending`` (a
    :class:`ShiftedAdditions` on ``dsi``) the shifted additions are recorded
    there, to be added with other groups' (its :meth:`~ShiftedAdditions.flush`);
    without it they are added before returning.
    """
    _, height, width = dsi.shape
    if not len(positions) or not transfer.valid.any():
        return
    box = _canvas(positions, transfer, width, height)
    if box is None:
        return
    x0, y0, x1, y1 = box[0] - 1, box[1] - 1, box[2], box[3]
    canvas_w, canvas_h = x1 - x0 + 1, y1 - y0 + 1
    additions = ShiftedAdditions(dsi, 0) if pending is None else pending
    if canvas_w * canvas_h > _MAX_CANVAS_IMAGES * width * height:
        additions.flush()
        splat_votes(dsi, positions, transfer)
        return
    planes = np.flatnonzero(transfer.valid)
    centre = np.array([x0 + x1, y0 + y1]) / 2.0
    half_diagonal = 0.5 * float(np.hypot(canvas_w, canvas_h))
    shifted = np.abs(transfer.scales[planes] - 1.0) * half_diagonal <= 0.5 / subpixel
    if shifted.any():
        moving = planes[shifted]
        # x_i = a x + b = x + b + (a - 1) x, with (a - 1) x taken at the canvas centre; plane i reads
        # base pixel p - r / S = p + q + phase / S (r the shift in 1/S px).
        shift = transfer.offsets[moving] + (transfer.scales[moving, None] - 1.0) * centre
        q, phase = np.divmod(-np.round(shift * subpixel).astype(np.int64), subpixel)
        # The phases some plane needs (sorted), and each plane's rank among them.
        present = np.zeros((2, subpixel), bool)
        present[0, phase[:, 0]] = True
        present[1, phase[:, 1]] = True
        rank = np.cumsum(present, axis=1) - 1
        x_phases, y_phases = np.flatnonzero(present[0]), np.flatnonzero(present[1])
        x_index, y_index = rank[0, phase[:, 0]], rank[1, phase[:, 1]]
        images = additions.images(len(x_phases) * len(y_phases), canvas_h, canvas_w)
        _phase_images(positions, x0, y0, canvas_w, canvas_h, subpixel, x_phases, y_phases,
                      images.reshape(len(y_phases), len(x_phases), canvas_h, canvas_w))
        additions.add(moving, y_index * len(x_phases) + x_index, q - np.array([x0, y0]))
    if not shifted.all():
        additions.flush()
        image = bilinear_splat((positions[None, :, 0] - x0), (positions[None, :, 1] - y0), None,
                               canvas_w, canvas_h)[0].astype(np.float32)
        for i in planes[~shifted]:
            _warp_add(dsi[i], image, float(transfer.scales[i]), transfer.offsets[i], x0, y0)
    if pending is None:
        additions.flush()
