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
The fast path, one splat per group of packets and one image addition per
plane, is :mod:`cmax.emvs.gather`. Votes that fall outside the reference
image are outside the DSI and are not counted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cmax._jit import kernel

__all__ = ["plane_depths", "PlaneTransfer", "plane_transfer", "plane_transfers", "base_plane_homographies",
           "project_packets", "splat_votes", "bilinear_splat"]

#: Votes per np.bincount call of :func:`splat_votes` (bounds its temporaries).
_VOTES_PER_CHUNK = 1 << 21


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


def plane_transfers(centres_ref: np.ndarray, depths: np.ndarray, K: np.ndarray) -> list[PlaneTransfer | None]:
    """Transfers of base-plane pixels to every plane for camera centres ``C`` (G, 3) in the reference frame.

    For each centre the base plane is the middle (in index, i.e. inverse depth)
    of the planes in front of ``C``; ``None`` when no plane is in front of it.
    One vectorized pass over all centres (G, n_planes).
    """
    centres_ref = np.asarray(centres_ref, dtype=np.float64).reshape(-1, 3)
    cz = centres_ref[:, 2:3]
    valid = depths[None] > cz + 1e-6 * np.abs(depths)[None]
    count = valid.sum(axis=1)
    base = np.argmax(np.cumsum(valid, axis=1) > (count // 2)[:, None], axis=1)
    z_b = depths[base][:, None]
    with np.errstate(divide="ignore", invalid="ignore"):  # rows without a valid plane are dropped
        lam = np.where(valid, (depths[None] - cz) / (z_b - cz), 0.0)
    scales = lam * z_b / depths[None]
    c = (1.0 - lam)[..., None] * centres_ref[:, None, :2] / depths[None, :, None]
    offsets = (1.0 - scales)[..., None] * K[:2, 2] + c @ K[:2, :2].T
    return [PlaneTransfer(int(base[g]), scales[g], offsets[g], valid[g]) if count[g] else None
            for g in range(len(centres_ref))]


def plane_transfer(centre_ref: np.ndarray, depths: np.ndarray, K: np.ndarray) -> PlaneTransfer | None:
    """Transfer of base-plane pixels to every plane for a camera centre ``C`` (3,) in the reference frame.

    The base plane is the middle (in index, i.e. inverse depth) of the planes
    in front of ``C``; ``None`` when no plane is in front of it (:func:`plane_transfers`).
    """
    return plane_transfers(np.asarray(centre_ref)[None], depths, K)[0]


def base_plane_homographies(T_ref_c: np.ndarray, z_base: float | np.ndarray, K: np.ndarray) -> np.ndarray:
    """Plane-induced homographies (k, 3, 3) from event pixels to the reference view via ``Z_ref = z_base``.

    For a camera ``T_ref_c = [R | C]`` the ray of pixel ``x`` meets the plane at
    ``P = C + s R K^-1 x``, ``s = (z_base - C_z) / (R K^-1 x)_z``, seen at ``K P / z_base``:

        H = K (C e_3^T + (z_base - C_z) I) R K^-1,

    and the third component of ``H x`` is ``z_base (R K^-1 x)_z``: positive exactly
    when the ray points towards the plane (for ``z_base > C_z``). ``z_base`` [m] is
    one depth for all cameras or one per camera (k,).
    """
    R = T_ref_c[:, :3, :3]
    C = T_ref_c[:, :3, 3]
    middle = C[:, :, None] * np.array([0.0, 0.0, 1.0]) + (z_base - C[:, 2])[:, None, None] * np.eye(3)
    return K @ middle @ R @ np.linalg.inv(K)


@kernel
def _project(pixels, homographies, starts, out, hits):
    """``out[i] = (H x_i)_xy / (H x_i)_z`` with ``H`` the homography of the packet ``[starts[j], starts[j + 1])``
    holding pixel ``i``; where ``(H x_i)_z <= 0`` (``hits[i]`` False) the division is by 1."""
    for j in range(len(starts) - 1):
        H = homographies[j]
        for i in range(starts[j], starts[j + 1]):
            x, y = np.float64(pixels[i, 0]), np.float64(pixels[i, 1])
            u = x * H[0, 0] + y * H[0, 1] + H[0, 2]
            v = x * H[1, 0] + y * H[1, 1] + H[1, 2]
            w = x * H[2, 0] + y * H[2, 1] + H[2, 2]
            hit = w > 0
            if not hit:
                w = 1.0
            hits[i] = hit
            out[i, 0] = u / w
            out[i, 1] = v / w


def project_packets(pixels: np.ndarray, homographies: np.ndarray, sizes: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Apply one homography per packet of consecutive pixels (one compiled pass).

    Parameters
    ----------
    pixels : ndarray, shape (N, 2)
        Undistorted event pixels ``(x, y)``.
    homographies : ndarray, shape (k, 3, 3)
        From :func:`base_plane_homographies`.
    sizes : ndarray, shape (k,)
        Events per packet (sum N).

    Returns
    -------
    positions : ndarray, shape (N, 2), float64
        Base-plane pixels of the reference view (meaningless where not ``hits``).
    hits : ndarray, shape (N,), bool
        Rays that meet the plane in front of their camera.
    """
    sizes = np.asarray(sizes, dtype=np.int64)
    if len(sizes) != len(homographies) or sizes.sum() != len(pixels):
        raise ValueError(f"{len(homographies)} homographies and packet sizes summing to {sizes.sum()} "
                         f"for {len(sizes)} packets of {len(pixels)} pixels")
    starts = np.concatenate([[0], np.cumsum(sizes)])
    out = np.empty((len(pixels), 2))
    hits = np.empty(len(pixels), bool)
    _project(np.ascontiguousarray(pixels), np.ascontiguousarray(homographies, dtype=np.float64), starts, out, hits)
    return out, hits


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
