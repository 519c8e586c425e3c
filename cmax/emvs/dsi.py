"""The Disparity Space Image of EMVS: planes, the plane-induced transfer and the two ways of voting.

Geometry (Rebecq et al., "EMVS: Event-based multi-view stereo", IJCV 2018,
doi:10.1007/s11263-018-1106-2, section 4). The DSI lives on a reference view
``T_w_ref`` with the event camera's pinhole ``K`` (undistorted pixels): plane
``i`` is ``Z_ref = z_i``, the planes uniform in inverse depth. An event at
undistorted pixel ``x`` seen from a camera with pose ``T_ref_c = [R | C]`` in
the reference frame back-projects along ``C + s R K^-1 x``. It meets the base
plane ``z_b`` at ``P_b`` (the full plane-induced homography) and plane ``z_i``
at ``C + lambda_i (P_b - C)`` with ``lambda_i = (z_i - C_z) / (z_b - C_z)``;
projected into the reference view this is the **affine transfer**

    x_i = a_i x_b + b_i,   a_i = lambda_i z_b / z_i,
    b_i = (1 - a_i) c + K_2 C_xy (1 - lambda_i) / z_i

(``c`` the principal point, ``K_2`` the upper-left 2x2 block of ``K``): one
scale and one offset per plane, depending only on the camera centre ``C``.

Voting. :func:`splat_votes` adds the exact bilinear votes of every event on
every plane (4 weights per event and plane, one compiled loop): the reference.
:func:`gather_votes` is the fast path. Events of consecutive packets whose
camera centres stay close share one transfer; they are splatted once
(bilinear) on the base plane, on grids shifted by multiples of ``1/S`` px.
A plane whose transfer is a translation (camera moving parallel to the
image plane) then receives the grid of its sub-pixel phase added at an
integer offset (the exact bilinear votes, offset rounded to ``1/S`` px), so
the cost per plane is one image addition whatever the number of events.
Scaled planes (motion along the optical axis) receive the splat resampled by
``cv2.warpAffine`` (times ``1 / a_i**2``, one vote per event and plane).
Votes that fall outside the reference image are outside the DSI and are not
counted.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cmax._jit import kernel

__all__ = ["plane_depths", "PlaneTransfer", "plane_transfer", "base_plane_homographies", "project_packets",
           "splat_votes", "gather_votes", "bilinear_splat"]

#: Votes per np.bincount call of :func:`splat_votes` (bounds its temporaries).
_VOTES_PER_CHUNK = 1 << 21
#: A gather canvas larger than this many reference images falls back to splatting.
_MAX_CANVAS_IMAGES = 16
#: Shifted images are splatted directly (not box-filtered from a fine grid) below this many
#: event-shifts per fine-grid cell.
_DIRECT_SPLATS_PER_CELL = 4


def plane_depths(depth_range: tuple[float, float], n_planes: int) -> np.ndarray:
    """Depths (n_planes,) float64 [m] of planes uniform in inverse depth, nearest first.

    Examples
    --------
    >>> plane_depths((1.0, 4.0), 3).tolist()
    [1.0, 1.6, 4.0]
    """
    near, far = depth_range
    return 1.0 / np.linspace(1.0 / near, 1.0 / far, n_planes)


@dataclass(frozen=True)
class PlaneTransfer:
    """The affine transfer from the base plane to every plane for one camera centre.

    Attributes
    ----------
    base : int
        Index of the base plane.
    scales : ndarray, shape (n_planes,), float64
        ``a_i`` (positive where ``valid``).
    offsets : ndarray, shape (n_planes, 2), float64
        ``b_i`` [px].
    valid : ndarray, shape (n_planes,), bool
        Planes in front of the camera centre (``z_i > C_z``); the others get no votes.
    """

    base: int
    scales: np.ndarray
    offsets: np.ndarray
    valid: np.ndarray


def plane_transfer(centre_ref: np.ndarray, depths: np.ndarray, K: np.ndarray) -> PlaneTransfer | None:
    """Transfer of base-plane pixels to every plane for a camera centre ``C`` (3,) in the reference frame.

    The base plane is the middle (in index, i.e. inverse depth) of the planes
    in front of ``C``; ``None`` when no plane is in front of it.
    """
    cz = centre_ref[2]
    valid = depths > cz + 1e-6 * np.abs(depths)
    if not valid.any():
        return None
    indices = np.flatnonzero(valid)
    base = int(indices[len(indices) // 2])
    z_b = depths[base]
    lam = np.where(valid, (depths - cz) / (z_b - cz), 0.0)
    scales = lam * z_b / depths
    c = (1.0 - lam)[:, None] * centre_ref[None, :2] / depths[:, None]
    offsets = (1.0 - scales)[:, None] * K[None, :2, 2] + c @ K[:2, :2].T
    return PlaneTransfer(base, scales, offsets, valid)


def base_plane_homographies(T_ref_c: np.ndarray, z_base: float, K: np.ndarray) -> np.ndarray:
    """Plane-induced homographies (k, 3, 3) from event pixels to the reference view via ``Z_ref = z_base``.

    For a camera ``T_ref_c = [R | C]`` the ray of pixel ``x`` meets the plane at
    ``P = C + s R K^-1 x``, ``s = (z_base - C_z) / (R K^-1 x)_z``, seen at ``K P / z_base``:

        H = K (C e_3^T + (z_base - C_z) I) R K^-1,

    and the third component of ``H x`` is ``z_base (R K^-1 x)_z``: positive exactly
    when the ray points towards the plane (for ``z_base > C_z``).
    """
    R = T_ref_c[:, :3, :3]
    C = T_ref_c[:, :3, 3]
    middle = C[:, :, None] * np.array([0.0, 0.0, 1.0]) + (z_base - C[:, 2])[:, None, None] * np.eye(3)
    return K @ middle @ R @ np.linalg.inv(K)


def project_packets(pixels: np.ndarray, homographies: np.ndarray, sizes: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Apply one homography per packet of consecutive pixels.

    Parameters
    ----------
    pixels : ndarray, shape (N, 2)
        Undistorted event pixels ``(x, y)``.
    homographies : ndarray, shape (k, 3, 3)
        From :func:`base_plane_homographies`.
    sizes : ndarray, shape (k,)
        Events per packet (sum N); all but the last equal.

    Returns
    -------
    positions : ndarray, shape (N, 2), float64
        Base-plane pixels of the reference view (meaningless where not ``hits``).
    hits : ndarray, shape (N,), bool
        Rays that meet the plane in front of their camera.
    """
    out = np.empty((len(pixels), 3))
    full = len(sizes) - 1 if len(sizes) > 1 and sizes[-1] != sizes[0] else len(sizes)
    split = int(sizes[0]) * full
    for start, stop, H in ((0, split, homographies[:full]), (split, len(pixels), homographies[full:])):
        if stop > start:
            xy = pixels[start:stop].astype(np.float64).reshape(len(H), -1, 2)
            out[start:stop] = (xy @ H[:, :, :2].transpose(0, 2, 1) + H[:, None, :, 2]).reshape(-1, 3)
    hits = out[:, 2] > 0
    depth = np.where(hits, out[:, 2], 1.0)
    return out[:, :2] / depth[:, None], hits


@kernel
def _splat_layers(x, y, weights, out):
    """Add bilinear votes of points (m, N) to ``out`` (m, H, W) float64; corners outside are dropped.

    ``weights`` is (m, N), or (0, 0) for unit weights.
    """
    layers, n = x.shape
    height, width = out.shape[1], out.shape[2]
    weighted = weights.size > 0
    for k in range(layers):
        for i in range(n):
            xf, yf = np.floor(x[k, i]), np.floor(y[k, i])
            if not (xf >= -1 and xf < width and yf >= -1 and yf < height):
                continue
            ix, iy = int(xf), int(yf)
            fx, fy = x[k, i] - xf, y[k, i] - yf
            w = weights[k, i] if weighted else 1.0
            wy0, wy1 = (1.0 - fy) * w, fy * w
            if iy >= 0:
                if ix >= 0:
                    out[k, iy, ix] += wy0 * (1.0 - fx)
                if ix + 1 < width:
                    out[k, iy, ix + 1] += wy0 * fx
            if iy + 1 < height:
                if ix >= 0:
                    out[k, iy + 1, ix] += wy1 * (1.0 - fx)
                if ix + 1 < width:
                    out[k, iy + 1, ix + 1] += wy1 * fx


def bilinear_splat(x: np.ndarray, y: np.ndarray, weights: np.ndarray | None, width: int,
                   height: int) -> np.ndarray:
    """Bilinear votes of points on ``m`` layers: ``x``, ``y`` (m, N) -> (m, height, width) float64.

    Each point adds ``weight * (1 - |x - X|) (1 - |y - Y|)`` to its four
    neighbouring pixels ``(X, Y)``; corners outside the image are not counted.
    One compiled pass over the points (:func:`_splat_layers`).
    """
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    w = (np.zeros((0, 0)) if weights is None
         else np.ascontiguousarray(np.broadcast_to(weights, x.shape), dtype=np.float64))
    out = np.zeros((x.shape[0], height, width))
    _splat_layers(x, y, w, out)
    return out


def splat_votes(dsi: np.ndarray, positions: np.ndarray, transfer: PlaneTransfer) -> None:
    """Add the exact bilinear votes of base-plane positions (N, 2) on every valid plane to ``dsi`` (in place)."""
    _, height, width = dsi.shape
    planes = np.flatnonzero(transfer.valid)
    if not len(positions) or not len(planes):
        return
    step = max(1, _VOTES_PER_CHUNK // len(positions))
    for start in range(0, len(planes), step):
        chunk = planes[start: start + step]
        a = transfer.scales[chunk, None]
        x = a * positions[None, :, 0] + transfer.offsets[chunk, 0, None]
        y = a * positions[None, :, 1] + transfer.offsets[chunk, 1, None]
        dsi[chunk] += bilinear_splat(x, y, None, width, height).astype(np.float32)


def _canvas(positions: np.ndarray, transfer: PlaneTransfer, width: int, height: int
            ) -> tuple[int, int, int, int] | None:
    """Base-plane rectangle ``(x0, y0, x1, y1)`` (inclusive) holding every vote that reaches the image."""
    planes = transfer.valid
    a = transfer.scales[planes]
    b = transfer.offsets[planes]
    # Base-plane points that some plane maps into [-1, W] x [-1, H] (the reach of a bilinear gather).
    reach_lo = np.min((-1.0 - b) / a[:, None], axis=0)
    reach_hi = np.max((np.array([width, height]) - b) / a[:, None], axis=0)
    xs, ys = positions[:, 0], positions[:, 1]
    lo = np.maximum(np.floor([xs.min(), ys.min()]), np.floor(reach_lo))
    hi = np.minimum(np.floor([xs.max(), ys.max()]) + 1, np.ceil(reach_hi))
    if np.any(hi < lo):
        return None
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _phase_images(positions: np.ndarray, x0: int, y0: int, width: int, height: int, subpixel: int,
                  x_phases: np.ndarray, y_phases: np.ndarray) -> np.ndarray:
    """Bilinear votes (len(y_phases), len(x_phases), height, width) float32 on sub-pixel-shifted grids.

    Layer ``[m, n]`` holds the cells centred at base-plane pixels
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
        shift_x = np.tile(x_phases / S, len(y_phases))[:, None]
        shift_y = np.repeat(y_phases / S, len(x_phases))[:, None]
        u = positions[None, :, 0] - x0 - shift_x
        v = positions[None, :, 1] - y0 - shift_y
        images = bilinear_splat(u, v, None, width, height).astype(np.float32)
        return images.reshape(len(y_phases), len(x_phases), height, width)
    u = (positions[:, 0] - x0 - (x_phases[0] / S if sx == 1 else 0.0)) * sx
    v = (positions[:, 1] - y0 - (y_phases[0] / S if sy == 1 else 0.0)) * sy
    fine = bilinear_splat(u[None], v[None], None, sx * width, sy * height)[0].astype(np.float32)
    if sx == sy == 1:
        return fine[None, None]
    once = cv2.boxFilter(fine, -1, (sx, sy), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    tent = cv2.boxFilter(once, -1, (sx, sy), anchor=(sx - 1, sy - 1), normalize=True,
                         borderType=cv2.BORDER_CONSTANT)
    # tent[sy l + j, sx k + i] is cell (l, k) of the grid shifted by (i, j) / S.
    grid = tent.reshape(height, sy, width, sx)
    rows = y_phases if sy > 1 else np.zeros(1, np.int64)
    cols = x_phases if sx > 1 else np.zeros(1, np.int64)
    return np.ascontiguousarray(grid[:, rows][:, :, :, cols].transpose(1, 3, 0, 2))


def _add_at_offset(target: np.ndarray, image: np.ndarray, qx: int, qy: int) -> None:
    """``target[p] += image[p + q]`` over the overlap (integer offset ``q``, in place)."""
    height, width = target.shape
    image_h, image_w = image.shape
    lo_x, lo_y = max(0, -qx), max(0, -qy)
    hi_x, hi_y = min(width, image_w - qx), min(height, image_h - qy)
    if hi_x <= lo_x or hi_y <= lo_y:
        return
    region = target[lo_y:hi_y, lo_x:hi_x]
    cv2.add(region, image[lo_y + qy: hi_y + qy, lo_x + qx: hi_x + qx], dst=region)


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


def gather_votes(dsi: np.ndarray, positions: np.ndarray, transfer: PlaneTransfer, *, subpixel: int = 4) -> None:
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
    back to :func:`splat_votes` when the events spread over a base-plane
    area of more than 16 reference images.
    """
    _, height, width = dsi.shape
    if not len(positions) or not transfer.valid.any():
        return
    box = _canvas(positions, transfer, width, height)
    if box is None:
        return
    x0, y0, x1, y1 = box[0] - 1, box[1] - 1, box[2], box[3]
    canvas_w, canvas_h = x1 - x0 + 1, y1 - y0 + 1
    if canvas_w * canvas_h > _MAX_CANVAS_IMAGES * width * height:
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
        x_phases, x_index = np.unique(phase[:, 0], return_inverse=True)
        y_phases, y_index = np.unique(phase[:, 1], return_inverse=True)
        images = _phase_images(positions, x0, y0, canvas_w, canvas_h, subpixel, x_phases, y_phases)
        for i, (qx, qy), n, m in zip(moving, q, x_index, y_index):
            _add_at_offset(dsi[i], images[m, n], int(qx) - x0, int(qy) - y0)
    if not shifted.all():
        image = bilinear_splat((positions[None, :, 0] - x0), (positions[None, :, 1] - y0), None,
                               canvas_w, canvas_h)[0].astype(np.float32)
        for i in planes[~shifted]:
            _warp_add(dsi[i], image, float(transfer.scales[i]), transfer.offsets[i], x0, y0)
