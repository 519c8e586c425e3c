"""Vectorized ray casting of a :class:`PlanarWorld` with torch: intensity and exact z-depth.

For a pinhole camera with intrinsics ``K`` at pose ``T_w_c``, the ray of pixel
``q = (u, v, 1)`` is ``X_c = z K^-1 q`` (z = depth). A plane through ``p`` (camera
frame) with normal ``n`` is hit at inverse depth ``w = 1/z = g . q`` with
``g = K^-T n / (n . p)``, an affine function of the pixel; the parallelogram
coordinates ``s, t`` and its texture coordinates are ratios ``(e . q) / w``
of affine functions (a homography). So per frame each parallelogram reduces
to a few 3-vectors, and a pixel lies on it when ``0 <= e_s . q <= w`` and
``0 <= e_t . q <= w`` (no division; this implies ``w >= 0``, in front).

The image is cut into tiles of ``tile`` x ``tile`` pixels; each parallelogram
is clipped to the near plane, projected, and paired with the tiles its
bounding box touches; pairs are dropped when the tile provably misses the
parallelogram or is covered by a nearer opaque one (tests at the four tile
corners, exact because the tests are linear in the pixel). All (pair, pixel)
tests run as one batched matmul plus element-wise comparisons; the z-buffer
keeps, per pixel, the largest inverse depth with a packed int64 key
``(bits(w) << 32) | index`` reduced by ``scatter_reduce(amax)``. Cut-out
parallelograms (alpha textures) test their alpha (nearest texel, level 0) in
the same pass. Finally each covered pixel is shaded by a trilinear
(mip-mapped) lookup -- two ``cv2.remap`` calls on the texture atlas -- whose
level comes from the analytic derivative of the texture coordinates with
respect to the pixel, so that far and grazing surfaces do not alias (which
would make spurious events). Pixels that hit nothing see the sky, a smooth
function of the ray's elevation, and get depth NaN.

Depth is exact up to float32 rounding of ``w``; there is no anti-aliasing of
geometric edges (a pixel shows the surface at its centre). Each frame runs
with the torch thread count of :func:`cmax._threads.torch_threads` (one
thread on a busy machine, where more would stall).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from cmax._threads import torch_threads_scope
from cmax.camera import Camera
from cmax.sim.textures import TextureAtlas
from cmax.sim.world import PlanarWorld

__all__ = ["Sky", "PlanarRenderer"]

_LITTLE_ENDIAN = sys.byteorder == "little"
_BITS_OF_ONE = int(np.float32(1.0).view(np.int32))


@dataclass(frozen=True)
class Sky:
    """Grey level of rays that hit nothing: ``horizon + (zenith - horizon) * max(e, 0)^0.6``.

    ``e`` is the sine of the ray's elevation above the plane normal to ``up``
    (world frame); below the horizon the level is ``ground`` blended in.
    """

    zenith: float = 200.0
    horizon: float = 235.0
    ground: float = 90.0
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        for name in ("zenith", "horizon", "ground"):
            value = getattr(self, name)
            if not 0.0 <= value <= 255.0:
                raise ValueError(f"{name} must be a grey level in [0, 255], got {value}")


class PlanarRenderer:
    """Renders a :class:`PlanarWorld` seen by ``camera`` at any pose.

    Parameters
    ----------
    world : PlanarWorld
    camera : Camera
        Pinhole intrinsics and image size (distortion is ignored: the renderer
        makes ideal pinhole images).
    sky : Sky
    near : float
        Near clipping distance [m] for the projected bounds: parts of surfaces
        closer than this may be missing.
    tile : int
        Tile side in pixels for binning (8, 16 or 32).
    texture_size : int
        Level-0 side of the texture atlas (textures are resized to it).
    """

    def __init__(self, world: PlanarWorld, camera: Camera, *, sky: Sky = Sky(), near: float = 0.05,
                 tile: int = 16, texture_size: int = 512) -> None:
        if not isinstance(world, PlanarWorld):
            raise TypeError(f"world must be a PlanarWorld, got {type(world).__name__}")
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a cmax.Camera, got {type(camera).__name__}")
        if not near > 0:
            raise ValueError(f"near must be positive (metres), got {near}")
        if tile not in (8, 16, 32):
            raise ValueError(f"tile must be 8, 16 or 32, got {tile}")
        self.world, self.camera, self.sky, self.near, self.tile = world, camera, sky, float(near), tile
        self.atlas = TextureAtlas.build(world.textures, texture_size)
        self._tex_alpha = torch.from_numpy(self.atlas.alpha)
        # Per parallelogram: atlas cell of its texture and its gain.
        cells = self.atlas.origins[:, 0][world.texture_ids]
        self._rect_table = np.column_stack([cells, world.gains]).astype(np.float64)  # (R, 3)
        self._tex_ids = torch.from_numpy(world.texture_ids.astype(np.int32))
        self._footprint = self._footprint_scale(world, camera)
        self._cutout = world.cutout
        self._corners = world.corners()
        self._K_inv = np.linalg.inv(camera.K)
        self.ntx = -(-camera.width // tile)
        self.nty = -(-camera.height // tile)
        lv, lu = np.mgrid[0:tile, 0:tile]
        self._local = torch.from_numpy(
            np.stack([lu.ravel(), lv.ravel(), np.ones(tile * tile)]).astype(np.float32)
        )  # (3, T*T)
        # Pixels are processed on the grid padded to whole tiles (Hp, Wp), row-major.
        self._Hp, self._Wp = self.nty * tile, self.ntx * tile
        self._pixel_in_tile = torch.from_numpy((lv * self._Wp + lu).ravel().astype(np.int64))
        v, u = np.mgrid[0: camera.height, 0: camera.width]  # shading runs on the image itself
        pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)  # (H*W, 3) float64
        self._u = torch.from_numpy(pixels[:, 0].astype(np.float32))
        self._v = torch.from_numpy(pixels[:, 1].astype(np.float32))
        rays = pixels @ self._K_inv.T  # z = 1
        self._rays_c = torch.from_numpy(rays.astype(np.float32))
        self._inv_ray_norm = torch.from_numpy(1.0 / np.linalg.norm(rays, axis=1)).to(torch.float32)
        self._ray_norm2 = torch.from_numpy((rays * rays).sum(1).astype(np.float32))

    @staticmethod
    def _footprint_scale(world: PlanarWorld, camera: Camera) -> np.ndarray:
        """(R,) ``k |n| / f``: per-frame division by ``|n . p|`` gives the mip-level constant.

        A pixel's footprint on a plane, in texels, is at most
        ``k r / (f cos(theta))`` (``r`` the range, ``theta`` the angle between
        ray and normal, ``k`` the texels per metre of the texture map (the
        geometric mean of its two scales for anisotropic maps),
        ``f`` the focal length); with ``r = |d| / w`` and
        ``cos(theta) = |w (n . p)| / (|n| |d|)`` (``d = K^-1 q``) that is
        ``k |n| |d|^2 / (f |n . p| w^2)``, used as ``2^lod``.
        """
        edges = np.stack([world.edges_u, world.edges_v], axis=2)  # (R, 3, 2)
        jacobian = world.texel_maps[:, :, :2] @ np.linalg.pinv(edges)  # (R, 2, 3) texels per metre
        singular = np.linalg.svd(jacobian, compute_uv=False)  # (R, 2)
        k = np.sqrt(singular[:, 0] * singular[:, 1])  # geometric mean: anisotropic maps neither blur nor alias much
        normal = np.linalg.norm(np.cross(world.edges_u, world.edges_v), axis=1)
        return k * normal / np.sqrt(camera.fx * camera.fy)

    # -- per-frame geometry (numpy, R parallelograms) ---------------------------------------
    def _plane_coefficients(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R, 6, 3) rows g, e_s, e_t, E_x, E_y (see module docstring), (n . p, 0, 0); (R,) usable mask."""
        R_cw = T_w_c[:3, :3].T
        centre = T_w_c[:3, 3]
        w = self.world
        p = (w.origins - centre) @ R_cw.T
        u = w.edges_u @ R_cw.T
        v = w.edges_v @ R_cw.T
        n = np.cross(u, v)
        nn = np.einsum("ij,ij->i", n, n)
        h = np.einsum("ij,ij->i", n, p)
        usable = np.abs(h) > 1e-9 * np.sqrt(nn)  # the camera is not on the plane
        usable &= (w.facing == 0) | (w.facing * h < 0)  # back faces of one-sided parallelograms
        h = np.where(usable, h, 1.0)
        g = (n @ self._K_inv) / h[:, None]
        u_dual = np.cross(v, n) / nn[:, None]
        v_dual = np.cross(n, u) / nn[:, None]
        e_s = u_dual @ self._K_inv - np.einsum("ij,ij->i", u_dual, p)[:, None] * g
        e_t = v_dual @ self._K_inv - np.einsum("ij,ij->i", v_dual, p)[:, None] * g
        A = w.texel_maps
        E = A[:, :, 0:1] * e_s[:, None] + A[:, :, 1:2] * e_t[:, None] + A[:, :, 2:3] * g[:, None]
        # Row 5 holds (n . p, 0, 0), the plane's offset, for the texture footprint.
        offset = np.zeros_like(g)
        offset[:, 0] = np.where(usable, h, 1.0)
        return np.concatenate([g[:, None], e_s[:, None], e_t[:, None], E, offset[:, None]], axis=1), usable

    def _tile_bounds(self, T_w_c: np.ndarray) -> np.ndarray:
        """(R, 4) int tile ranges tx0, tx1, ty0, ty1 (inclusive); tx0 > tx1 where culled."""
        corners = (self._corners - T_w_c[:3, 3]) @ T_w_c[:3, :3]  # (R, 4, 3) camera frame
        a, b = corners, np.roll(corners, -1, axis=1)
        za, zb = a[..., 2] - self.near, b[..., 2] - self.near
        crosses = za * zb < 0
        frac = np.where(crosses, za / np.where(crosses, za - zb, 1.0), 0.0)
        cut = a + frac[..., None] * (b - a)
        points = np.concatenate([corners, cut], axis=1)  # (R, 8, 3)
        keep = np.concatenate([za >= 0, crosses], axis=1)
        z = np.where(keep, np.maximum(points[..., 2], self.near), 1.0)
        K = self.camera.K
        x = K[0, 0] * points[..., 0] / z + K[0, 1] * points[..., 1] / z + K[0, 2]
        y = K[1, 1] * points[..., 1] / z + K[1, 2]
        big = 1e9
        x0 = np.where(keep, x, big).min(axis=1)
        x1 = np.where(keep, x, -big).max(axis=1)
        y0 = np.where(keep, y, big).min(axis=1)
        y1 = np.where(keep, y, -big).max(axis=1)
        t = self.tile
        bounds = np.stack([
            np.floor(np.clip(x0, -t, self.ntx * t) / t), np.floor(np.clip(x1, -t, self.ntx * t) / t),
            np.floor(np.clip(y0, -t, self.nty * t) / t), np.floor(np.clip(y1, -t, self.nty * t) / t),
        ], axis=1).astype(np.int64)
        bounds[:, 0] = np.maximum(bounds[:, 0], 0)
        bounds[:, 1] = np.minimum(bounds[:, 1], self.ntx - 1)
        bounds[:, 2] = np.maximum(bounds[:, 2], 0)
        bounds[:, 3] = np.minimum(bounds[:, 3], self.nty - 1)
        bounds[~keep.any(axis=1), 0] = self.ntx  # entirely behind the near plane
        return bounds

    def _pairs(self, bounds: np.ndarray, usable: np.ndarray, coef: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(rect, tx, ty, alone) of every tile that may hold pixels of each parallelogram.

        ``alone`` marks pairs whose parallelogram covers the whole tile and is
        the tile's only candidate.

        Tiles of the bounding box are dropped when all four corner pixels fail
        the same one of the (affine) inside tests, which proves the whole tile
        misses the parallelogram, or when an opaque parallelogram that covers
        the whole tile is nearer than it everywhere in the tile.
        """
        nx = np.maximum(bounds[:, 1] - bounds[:, 0] + 1, 0)
        ny = np.maximum(bounds[:, 3] - bounds[:, 2] + 1, 0)
        counts = np.where(usable, nx * ny, 0)
        rect = np.repeat(np.arange(len(bounds)), counts)
        k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        tx = bounds[rect, 0] + k % nx[rect]
        ty = bounds[rect, 2] + k // nx[rect]
        T = self.tile
        # The five inside constraints a, w - a, b, w - b, w (all >= 0) at the four tile corners.
        g, e_s, e_t = coef[:, 0], coef[:, 1], coef[:, 2]
        C = np.stack([e_s, g - e_s, e_t, g - e_t, g], axis=1)[rect]  # (P, 5, 3)
        corners = np.empty((len(rect), 3, 4))
        corners[:, 0] = tx[:, None] * T + np.array([0, T - 1, 0, T - 1])
        corners[:, 1] = ty[:, None] * T + np.array([0, 0, T - 1, T - 1])
        corners[:, 2] = 1.0
        values = C @ corners  # (P, 5, 4)
        v0, v1, v2, v3 = values[..., 0], values[..., 1], values[..., 2], values[..., 3]
        high = np.maximum(np.maximum(v0, v1), np.maximum(v2, v3))  # (P, 5) largest over corners
        low = np.minimum(np.minimum(v0, v1), np.minimum(v2, v3))
        outside = high.min(axis=1) < 0
        # Occlusion: an opaque parallelogram containing all four corners covers the whole tile
        # (the inside tests are linear) at inverse depth >= its smallest corner value; a pair
        # whose largest corner w (w is affine) is below that is hidden everywhere in the tile.
        covers = (low.min(axis=1) >= 0) & ~self._cutout[rect]
        tile = ty * self.ntx + tx
        cover = np.zeros(self.ntx * self.nty)
        np.maximum.at(cover, tile[covers], low[covers, 4])
        keep = ~outside & (high[:, 4] >= cover[tile])
        # A tile left with a single pair that covers it needs no per-pixel test.
        survivors = np.bincount(tile[keep], minlength=self.ntx * self.nty)
        alone = covers[keep] & (survivors[tile[keep]] == 1)
        return rect[keep], tx[keep], ty[keep], alone

    # -- rendering --------------------------------------------------------------------
    def _zbuffer(self, coef: np.ndarray, usable: np.ndarray, T_w_c: np.ndarray) -> torch.Tensor:
        """(Hp*Wp,) int64 keys ``(bits(w) << 32) | rect`` per pixel of the padded grid; < 2^32 where nothing is hit.

        The float32 bits of a positive inverse depth ``w`` grow with ``w``, so
        the largest key is the nearest surface. Tiles covered by a single
        parallelogram are filled with ``bits(1.0)`` instead of ``w`` (callers
        recompute ``w``; only the rectangle index and the hit flag are used).
        """
        rect, tx, ty, alone = self._pairs(self._tile_bounds(T_w_c), usable, coef)
        T = self.tile
        keys = torch.zeros(self._Hp * self._Wp, dtype=torch.int64)
        if not len(rect):
            return keys
        if alone.any():
            start = torch.from_numpy(ty[alone] * T * self._Wp + tx[alone] * T)[:, None]
            fill = torch.from_numpy(rect[alone] + (_BITS_OF_ONE << 32))[:, None]
            keys.scatter_(0, (start + self._pixel_in_tile).view(-1), fill.expand(-1, T * T).reshape(-1))
        cutout = self._cutout[rect]
        zero = torch.zeros((), dtype=torch.float32)
        for select, rows in ((~cutout & ~alone, 3), (cutout, 5)):
            if not select.any():
                continue
            r, x0, y0 = rect[select], tx[select] * T, ty[select] * T
            M = coef[r, :rows]  # (P, rows, 3)
            shifted = M.copy()
            shifted[..., 2] = M[..., 0] * x0[:, None] + M[..., 1] * y0[:, None] + M[..., 2]
            shifted = np.ascontiguousarray(shifted.transpose(1, 0, 2), dtype=np.float32)  # (rows, P, 3)
            values = torch.matmul(torch.from_numpy(shifted), self._local)  # (rows, P, T*T)
            w, a, b = values[0], values[1], values[2]
            # 0 <= a, b <= w implies w >= 0 (w = 0 packs to a key below 2^32: no hit).
            valid = (torch.minimum(a, b) >= 0) & (torch.maximum(a, b) <= w)
            if rows == 5:
                valid &= self._alpha_at(values, w, torch.from_numpy(r))
            w_bits = torch.where(valid, w, zero).view(torch.int32)
            r_t = torch.from_numpy(r.astype(np.int32))[:, None].expand_as(w_bits)
            halves = [r_t, w_bits] if _LITTLE_ENDIAN else [w_bits, r_t]
            key = torch.stack(halves, dim=-1).view(torch.int64).view(w_bits.shape)  # (w_bits << 32) | r
            index = torch.from_numpy(y0 * self._Wp + x0)[:, None] + self._pixel_in_tile
            keys.scatter_reduce_(0, index.view(-1), key.view(-1), reduce="amax")
        return keys

    def _alpha_at(self, values: torch.Tensor, w: torch.Tensor, rect: torch.Tensor) -> torch.Tensor:
        """Opacity (P, T*T) of the cut-out texture at the hit points (nearest level-0 texel)."""
        size = self.atlas.size
        safe_w = torch.where(w > 0, w, torch.ones((), dtype=w.dtype))
        tx = torch.floor(values[3] / safe_w).to(torch.int64) & (size - 1)
        ty = torch.floor(values[4] / safe_w).to(torch.int64) & (size - 1)
        base = (self._tex_ids[rect].to(torch.int64) * size * size)[:, None]
        return self._tex_alpha[base + ty * size + tx]

    def render(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intensity and depth seen from ``T_w_c``.

        Parameters
        ----------
        T_w_c : ndarray, shape (4, 4)
            Camera-to-world pose.

        Returns
        -------
        intensity : ndarray, shape (H, W), float32
            Grey levels in [0, 255].
        depth : ndarray, shape (H, W), float32
            z-depth [m]; NaN where the ray hits nothing (sky).
        """
        T_w_c = np.asarray(T_w_c, dtype=np.float64)
        if T_w_c.shape != (4, 4) or not np.isfinite(T_w_c).all():
            raise ValueError(f"T_w_c must be a finite (4, 4) pose, got shape {T_w_c.shape}")
        with torch_threads_scope(self.camera.height * self.camera.width):
            return self._render(T_w_c)

    def _render(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        coef, usable = self._plane_coefficients(T_w_c)
        H, W = self.camera.height, self.camera.width
        keys = self._zbuffer(coef, usable, T_w_c).view(self._Hp, self._Wp)[:H, :W].reshape(-1)
        halves = keys.view(torch.int32).view(-1, 2)
        rect = halves[:, 0 if _LITTLE_ENDIAN else 1].to(torch.int64)
        hit = halves[:, 1 if _LITTLE_ENDIAN else 0] > 0
        intensity, depth = self._shade(rect, hit, coef)
        if not bool(hit.all()):
            intensity = torch.where(hit, intensity, self._sky(T_w_c))
            depth = torch.where(hit, depth, torch.full((), float("nan")))
        return intensity.view(H, W).numpy(), depth.view(H, W).numpy()

    def _shade(self, rect: torch.Tensor, hit: torch.Tensor, coef: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Grey levels and depth (H*W,) of the pixels on parallelograms ``rect``; garbage where not ``hit``.

        The depth is ``1 / (g . q)`` of the pixel's parallelogram, in float32.
        """
        table = np.concatenate([coef[:, [0, 3, 4]].reshape(len(coef), 9), self._rect_table,
                                self._footprint[:, None] / np.abs(coef[:, 5:6, 0])], axis=1)
        table = torch.from_numpy(np.ascontiguousarray(table.T, dtype=np.float32))
        c = torch.index_select(table, 1, rect)  # (13, P): g, E_x, E_y, cell x, cell y, gain, footprint
        u, v = self._u, self._v
        w = torch.addcmul(c[2], c[0], u).addcmul_(c[1], v)
        inv_w = torch.where(hit, torch.reciprocal(w), torch.zeros((), dtype=w.dtype))
        tx = torch.addcmul(c[5], c[3], u).addcmul_(c[4], v).mul_(inv_w)
        ty = torch.addcmul(c[8], c[6], u).addcmul_(c[7], v).mul_(inv_w)
        # Texels per pixel: rho = k |n| |d|^2 / (f |n . p| w^2) (see _footprint_scale).
        rho = (inv_w * inv_w).mul_(self._ray_norm2).mul_(c[12])
        lod = torch.log2(rho.clamp_min_(1e-12)).clamp_(0.0, self.atlas.levels - 1.0)
        values = self._trilinear(tx, ty, lod, c[9], c[10])
        return values.mul_(c[11]).clamp_(0.0, 255.0), inv_w

    def _trilinear(self, tx: torch.Tensor, ty: torch.Tensor, lod: torch.Tensor,
                   cell_x: torch.Tensor, cell_y: torch.Tensor) -> torch.Tensor:
        """Mip-mapped bilinear lookups at level-0 texel coordinates (wrapping), blended across levels.

        Level ``l`` (side ``S_l = S / 2^l``) of the texture whose atlas cell
        starts at ``cell`` is sampled at ``cell + origin_l + (x mod S_l)`` with
        ``x = tx S_l / S - 1/2`` (texel centres at integers, as cv2.remap
        wants); see :class:`TextureAtlas` for ``origin_l``.
        """
        S, levels = float(self.atlas.size), self.atlas.levels
        W = self.camera.width
        level = torch.floor(lod).clamp_(max=max(levels - 2, 0))
        side = torch.exp2(level.neg()).mul_(S)  # S_l
        above0 = level.clamp(max=1.0)  # 0 at level 0, else 1
        ax, ay = tx * (1.0 / S), ty * (1.0 / S)
        out = []
        for step in (0, 1) if levels > 1 else (0,):
            if step:
                side = side.mul_(0.5)
                above0 = 1.0
            # Atlas origin of level l inside the cell: (0, 0) for l = 0, else (S + 1, S - 2 S_l + l - 1).
            half = torch.reciprocal(side).mul_(0.5)
            fx = ax - half
            fx = fx.sub_(torch.floor(fx)).mul_(side).add_(cell_x)
            fy = ay - half
            fy = fy.sub_(torch.floor(fy)).mul_(side).add_(cell_y)
            if step:
                fx.add_(S + 1.0)
                fy.add_(level + (S - 1.0 + step)).sub_(side, alpha=2.0)
            else:
                fx.add_(above0, alpha=S + 1.0)
                fy.addcmul_(above0, torch.sub(level, side, alpha=2.0).add_(S - 1.0))
            sampled = cv2.remap(self.atlas.image, fx.view(-1, W).numpy(), fy.view(-1, W).numpy(), cv2.INTER_LINEAR)
            out.append(torch.from_numpy(sampled).view(-1))
        if len(out) == 1:
            return out[0]
        return torch.lerp(out[0], out[1], lod.sub_(level))

    def _sky(self, T_w_c: np.ndarray) -> torch.Tensor:
        """(H*W,) grey levels of the sky in every pixel's direction."""
        up_c = T_w_c[:3, :3].T @ np.asarray(self.sky.up, dtype=np.float64)
        up_c = torch.from_numpy((up_c / np.linalg.norm(up_c)).astype(np.float32))
        elevation = (self._rays_c @ up_c) * self._inv_ray_norm
        s = self.sky
        above = s.horizon + (s.zenith - s.horizon) * elevation.clamp(0.0, 1.0) ** 0.6
        below = s.horizon + (s.ground - s.horizon) * (elevation * -4.0).clamp(0.0, 1.0)
        return torch.where(elevation >= 0, above, below)
