"""Renderable scenes with ground truth: a camera, a trajectory, intensity and exact depth at any time.

Every scene has the same interface:

* ``scene.camera`` -- a :class:`cmax.Camera` (ideal pinhole);
* ``scene.render(t_s) -> (intensity, depth)`` -- float32 (H, W) grey levels
  in [0, 255] and z-depth [m] (NaN where unknown: sky, holes);
* ``scene.pose(t_s) -> T_w_c`` (4, 4), camera-to-world;
* ``scene.twist(t_s) -> (v, omega)`` (6,), camera frame, m/s and rad/s,
  with ``d/dt T_w_c = T_w_c hat(xi)``.

:class:`PlanarScene` ray-casts a piecewise-planar world (see
:mod:`cmax.sim.world` and :mod:`cmax.sim.render`); :class:`RGBDScene`
re-renders one real image with its depth map for small camera motions. The
presets (indoor flying, driving, hiking, ...) live in :mod:`cmax.sim.presets`.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping, Protocol, runtime_checkable

import cv2
import numpy as np

from cmax.camera import Camera, check_intrinsics
from cmax.geometry import invert_pose
from cmax.sim.render import PlanarRenderer, Sky
from cmax.sim.trajectories import Trajectory
from cmax.sim.world import PlanarWorld

__all__ = ["Scene", "SceneInfo", "PlanarScene", "RGBDScene", "TimeScaledScene", "warp_image"]


@runtime_checkable
class Scene(Protocol):
    """What :func:`cmax.sim.simulate_scene` needs from a scene."""

    camera: Camera

    def render(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (H, W) float32 [0, 255] and z-depth (H, W) float32 [m, NaN where unknown] at ``t_s`` [s]."""

    def pose(self, t_s: float) -> np.ndarray:
        """``T_w_c`` (4, 4) float64, the camera-to-world pose at ``t_s`` [s]."""

    def twist(self, t_s: float) -> np.ndarray:
        """Body twist ``(v [m/s], omega [rad/s])`` (6,) float64 in the camera frame at ``t_s`` [s]."""


@dataclass(frozen=True)
class SceneInfo:
    """What a scene promises over ``[0, duration_s]``.

    Attributes
    ----------
    name : str
    duration_s : float
        Length of the trajectory the world was built for [s].
    depth_range_m : (float, float)
        Bounds of the finite ground-truth depth [m] at every time.
    speed_range_mps : (float, float)
        Bounds of the camera speed ``|v|`` [m/s].
    max_angular_speed_dps : float
        Bound of ``|omega|`` [deg/s].
    description : str
    """

    name: str
    duration_s: float
    depth_range_m: tuple[float, float]
    speed_range_mps: tuple[float, float]
    max_angular_speed_dps: float
    description: str = ""


def _check_time(t_s: object) -> float:
    if isinstance(t_s, (bool, np.bool_)) or not isinstance(t_s, (int, float, np.integer, np.floating)):
        raise TypeError(f"t_s must be a number of seconds, got {type(t_s).__name__}")
    if not np.isfinite(t_s):
        raise ValueError(f"t_s must be finite, got {t_s}")
    return float(t_s)


class PlanarScene:
    """A piecewise-planar world seen by a camera moving along a trajectory.

    Parameters
    ----------
    world : PlanarWorld
    camera : Camera
    trajectory : Trajectory
        Gives ``pose(t_s)`` and ``twist(t_s)``.
    sky : Sky
        Grey levels of rays that hit nothing.
    info : SceneInfo, optional
        Stated ranges (presets fill it in).
    recommended_simulator : mapping, optional
        Keyword arguments for :class:`cmax.sim.esim.EventSimulator` that suit
        the scene (e.g. more noise at night); read-only.
    near : float
        Near clipping distance [m].
    texture_size : int
        Level-0 side of the texture atlas.

    Examples
    --------
    >>> import numpy as np
    >>> from cmax.sim.presets import make_scene
    >>> scene = make_scene("indoor_flying", width=64, height=48, texture_size=64)
    >>> intensity, depth = scene.render(0.5)
    >>> near, far = scene.info.depth_range_m   # what the scene promises [m]
    >>> intensity.shape, depth.dtype.name, bool(near <= np.nanmin(depth) and np.nanmax(depth) <= far)
    ((48, 64), 'float32', True)
    """

    def __init__(self, world: PlanarWorld, camera: Camera, trajectory: Trajectory, *, sky: Sky = Sky(),
                 info: SceneInfo | None = None, recommended_simulator: Mapping[str, Any] | None = None,
                 near: float = 0.05, texture_size: int = 512) -> None:
        if not isinstance(trajectory, Trajectory):
            raise TypeError(f"trajectory must have pose(t_s) and twist(t_s), got {type(trajectory).__name__}")
        self.world = world
        self.camera = camera
        self.trajectory = trajectory
        self.info = info
        self.recommended_simulator = MappingProxyType(dict(recommended_simulator or {}))
        self.renderer = PlanarRenderer(world, camera, sky=sky, near=near, texture_size=texture_size)

    def render(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (H, W) float32 [0, 255] and z-depth (H, W) float32 [m, NaN = sky] at ``t_s``."""
        return self.renderer.render(self.pose(_check_time(t_s)))

    def render_pose(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (H, W) float32 [0, 255] and z-depth (H, W) float32 [m, NaN = sky] seen from any camera-to-world
        pose ``T_w_c`` (4, 4)."""
        return self.renderer.render(T_w_c)

    def pose(self, t_s: float) -> np.ndarray:
        """``T_w_c`` (4, 4) float64 at ``t_s`` [s]."""
        return self.trajectory.pose(_check_time(t_s))

    def twist(self, t_s: float) -> np.ndarray:
        """Body twist ``(v [m/s], omega [rad/s])`` (6,) float64 in the camera frame at ``t_s``."""
        return self.trajectory.twist(_check_time(t_s))

    def __repr__(self) -> str:
        name = self.info.name if self.info else "custom"
        return (f"PlanarScene({name!r}, {len(self.world)} parallelograms, "
                f"{self.camera.width}x{self.camera.height})")


# -- RGB-D ---------------------------------------------------------------------------------
def warp_image(
    image_a: np.ndarray, depth_b: np.ndarray, T_a_b: np.ndarray, K: np.ndarray,
    *, depth_a: np.ndarray | None = None, occlusion_tolerance: float = 0.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Backward warp of view a into view b with the depth of view b.

    Each pixel ``x_b`` with depth ``d = depth_b[x_b]`` goes to
    ``x_a = pi(K T_a_b d K^-1 x_b)``, where ``image_a`` is sampled
    bilinearly (edge values repeated within half a pixel of the border).
    Pixels are valid where the depth is finite, ``x_a`` lies in the image's
    pixel area and in front of camera a, and -- when ``depth_a`` is given
    -- the point is not occluded in view a (``|depth_a[x_a] - z_a| <=
    occlusion_tolerance * z_a``, depth_a sampled at the nearest pixel).

    Parameters
    ----------
    image_a : ndarray, shape (H, W)
    depth_b : ndarray, shape (H, W)
        z-depth of view b [m], NaN where unknown.
    T_a_b : ndarray, shape (4, 4)
        Pose of camera b in the frame of camera a (``T_w_a^-1 T_w_b``).
    K : ndarray, shape (3, 3)
    depth_a : ndarray, shape (H, W), optional
    occlusion_tolerance : float

    Returns
    -------
    warped : ndarray, shape (H, W), float32
        ``image_a`` seen from b (0 where invalid).
    valid : ndarray, shape (H, W), bool
    """
    image_a = np.asarray(image_a, dtype=np.float32)
    depth_b = np.asarray(depth_b, dtype=np.float64)
    if image_a.ndim != 2 or depth_b.shape != image_a.shape:
        raise ValueError(f"image_a and depth_b must be (H, W) of one shape, got {image_a.shape}, {depth_b.shape}")
    K = check_intrinsics(K)
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    if T_a_b.shape != (4, 4):
        raise ValueError(f"T_a_b must have shape (4, 4), got {T_a_b.shape}")
    H, W = depth_b.shape
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3) @ np.linalg.inv(K).T
    points_b = rays * depth_b.reshape(-1, 1)
    points_a = points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    z = points_a[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        projected = (points_a @ K.T)[:, :2] / z[:, None]
    x, y = projected[:, 0], projected[:, 1]
    # Points that land within the image's pixel area (half a pixel beyond the outer centres).
    valid = np.isfinite(depth_b.ravel()) & (z > 1e-6) & (x >= -0.5) & (x <= W - 0.5) & (y >= -0.5) & (y <= H - 0.5)
    if depth_a is not None:
        depth_a = np.asarray(depth_a, dtype=np.float64)
        if depth_a.shape != (H, W):
            raise ValueError(f"depth_a must have shape {(H, W)}, got {depth_a.shape}")
        xi = np.clip(np.round(np.nan_to_num(x)), 0, W - 1).astype(int)
        yi = np.clip(np.round(np.nan_to_num(y)), 0, H - 1).astype(int)
        seen = depth_a[yi, xi]
        with np.errstate(invalid="ignore"):
            valid &= np.abs(seen - z) <= occlusion_tolerance * z
    map_x = np.where(valid, x, -10).astype(np.float32).reshape(H, W)
    map_y = np.where(valid, y, -10).astype(np.float32).reshape(H, W)
    warped = cv2.remap(image_a, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.where(valid.reshape(H, W), warped, 0).astype(np.float32), valid.reshape(H, W)


class TimeScaledScene:
    """A scene played ``factor`` times faster: the same world and path, ``factor`` x the speeds.

    ``render(t)``, ``pose(t)`` are the wrapped scene's at ``factor * t``; ``twist(t)`` is
    ``factor`` times its twist there (both ``v`` and ``omega`` scale). The parallax of a
    window of fixed length grows by ``factor``: a way to give slow scenes the few pixels
    of parallax depth estimation needs without a longer window or a larger sensor.

    Parameters
    ----------
    scene : Scene
        Built for a trajectory of at least ``factor`` x the duration to be simulated.
    factor : float
        Speed-up (> 0; < 1 slows the scene down).

    Examples
    --------
    >>> import numpy as np
    >>> from cmax.sim.presets import make_scene
    >>> base = make_scene("slider", seed=1, width=32, height=24, duration_s=2.0, texture_size=64)
    >>> fast = TimeScaledScene(base, 2.0)
    >>> bool(np.allclose(fast.twist(0.25), 2.0 * base.twist(0.5)))
    True
    """

    def __init__(self, scene: Scene, factor: float) -> None:
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must have camera, render, pose and twist, got {type(scene).__name__}")
        if isinstance(factor, (bool, np.bool_)) or not isinstance(factor, (int, float, np.integer, np.floating)) \
                or not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"factor must be a finite number > 0, got {factor!r}")
        self.scene, self.factor = scene, float(factor)
        self.camera = scene.camera
        self.recommended_simulator = getattr(scene, "recommended_simulator", MappingProxyType({}))
        info = getattr(scene, "info", None)
        self.info = None if info is None else SceneInfo(
            f"{info.name}_x{self.factor:g}", info.duration_s / self.factor, info.depth_range_m,
            (info.speed_range_mps[0] * self.factor, info.speed_range_mps[1] * self.factor),
            info.max_angular_speed_dps * self.factor,
            f"{info.description} (played {self.factor:g}x faster)".strip())

    def render(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (H, W) float32 and z-depth (H, W) float32 [m] of the wrapped scene at ``factor * t_s`` [s]."""
        return self.scene.render(self.factor * _check_time(t_s))

    def pose(self, t_s: float) -> np.ndarray:
        """``T_w_c`` (4, 4) of the wrapped scene at ``factor * t_s``."""
        return self.scene.pose(self.factor * _check_time(t_s))

    def twist(self, t_s: float) -> np.ndarray:
        """``factor`` x the wrapped scene's body twist ``(v, omega)`` (6,) at ``factor * t_s`` [m/s, rad/s]."""
        return self.factor * np.asarray(self.scene.twist(self.factor * _check_time(t_s)), dtype=np.float64)

    def __repr__(self) -> str:
        return f"TimeScaledScene({self.scene!r}, factor={self.factor:g})"


class RGBDScene:
    """One real image and its depth map, re-rendered for small camera motions.

    The reference view sits at ``T_w_ref`` (identity by default). At time t the
    depth of the new view is made by forward-warping the reference depth with
    a z-buffer (nearest pixel, smallest depth wins), then refined by two
    fixed-point steps against the reference depth; intensities are then fetched by backward warping (bilinear).
    Pixels that the reference view does not see (disocclusions, outside its
    field of view) get depth NaN, and their intensities are filled by OpenCV's
    Telea inpainting: plausible but not ground truth. Use motions of a few
    percent of the scene depth. The refinement samples the reference inverse
    depth bilinearly, which is exact on planar patches.

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3)
        Grey or BGR image, uint8 or float in [0, 255].
    depth : ndarray, shape (H, W)
        z-depth of the image [m]; NaN or <= 0 where unknown.
    K : ndarray, shape (3, 3)
        Intrinsics of the image.
    trajectory : Trajectory
    T_w_ref : ndarray, shape (4, 4), optional
        Pose of the reference view.
    """

    def __init__(self, image: np.ndarray, depth: np.ndarray, K: np.ndarray, trajectory: Trajectory,
                 *, T_w_ref: np.ndarray | None = None) -> None:
        image = np.asarray(image)
        if image.ndim == 3 and image.shape[2] == 3:
            image = cv2.cvtColor(image.astype(np.float32), cv2.COLOR_BGR2GRAY)
        if image.ndim != 2:
            raise ValueError(f"image must have shape (H, W) or (H, W, 3), got {image.shape}")
        image = image.astype(np.float32)
        if not np.isfinite(image).all() or image.min() < 0 or image.max() > 255:
            raise ValueError("image must hold finite grey levels in [0, 255]")
        depth = np.asarray(depth, dtype=np.float64)
        if depth.shape != image.shape:
            raise ValueError(f"depth must have shape {image.shape}, got {depth.shape}")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
        if not np.isfinite(depth).any():
            raise ValueError("depth has no valid (finite, positive) value")
        if not isinstance(trajectory, Trajectory):
            raise TypeError(f"trajectory must have pose(t_s) and twist(t_s), got {type(trajectory).__name__}")
        H, W = image.shape
        self.camera = Camera(check_intrinsics(K), W, H)
        self.image, self.depth, self.trajectory = image, depth, trajectory
        self.T_w_ref = np.eye(4) if T_w_ref is None else np.asarray(T_w_ref, dtype=np.float64)
        if self.T_w_ref.shape != (4, 4):
            raise ValueError(f"T_w_ref must have shape (4, 4), got {self.T_w_ref.shape}")
        v, u = np.mgrid[0:H, 0:W]
        rays = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3) @ np.linalg.inv(self.camera.K).T
        valid = np.isfinite(depth.ravel())
        self._points_ref = (rays * depth.reshape(-1, 1))[valid]
        self._inverse_depth = (1.0 / depth).astype(np.float32)  # NaN where unknown

    def pose(self, t_s: float) -> np.ndarray:
        """``T_w_c`` (4, 4) at ``t_s`` [s]."""
        return self.trajectory.pose(_check_time(t_s))

    def twist(self, t_s: float) -> np.ndarray:
        """Body twist ``(v, omega)`` (6,) at ``t_s`` [s], camera frame."""
        return self.trajectory.twist(_check_time(t_s))

    def render(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (H, W) float32 and z-depth (H, W) float32 [m, NaN where unknown] at ``t_s``."""
        return self.render_pose(self.pose(t_s))

    def render_pose(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intensity (H, W) float32 and z-depth (H, W) float32 [m, NaN where unknown] seen from any camera-to-world
        pose ``T_w_c`` (4, 4): the reference image warped by its depth, occluded pixels NaN."""
        T_c_ref = invert_pose(T_w_c) @ self.T_w_ref
        depth = self._forward_depth(T_c_ref)
        T_ref_c = invert_pose(T_c_ref)
        K = self.camera.K
        for _ in range(2):  # refine: depth of the reference surface seen through each pixel
            depth = self._refine(depth, T_ref_c, K)
        intensity, valid = warp_image(self.image, depth, T_ref_c, K, depth_a=self.depth, occlusion_tolerance=0.03)
        depth = np.where(valid, depth, np.nan)
        holes = (~valid).astype(np.uint8)
        if holes.any():
            scaled = np.clip(intensity, 0, 255).astype(np.uint8)
            filled = cv2.inpaint(scaled, holes, 3, cv2.INPAINT_TELEA).astype(np.float32)
            intensity = np.where(valid, intensity, filled)
        return intensity.astype(np.float32), depth.astype(np.float32)

    def _forward_depth(self, T_c_ref: np.ndarray) -> np.ndarray:
        H, W = self.image.shape
        points = self._points_ref @ T_c_ref[:3, :3].T + T_c_ref[:3, 3]
        z = points[:, 2]
        front = z > 1e-6
        points, z = points[front], z[front]
        pixels = points @ self.camera.K.T
        x = np.round(pixels[:, 0] / z).astype(np.int64)
        y = np.round(pixels[:, 1] / z).astype(np.int64)
        inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
        index, z = y[inside] * W + x[inside], z[inside]
        order = np.lexsort((z, index))  # by pixel, nearest first
        index, z = index[order], z[order]
        first = np.ones(len(index), bool)
        first[1:] = index[1:] != index[:-1]
        depth = np.full(H * W, np.inf)
        depth[index[first]] = z[first]
        depth = depth.reshape(H, W)
        # Close one-pixel cracks left by magnification with the nearest neighbouring depth.
        eroded = cv2.erode(depth.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.float64)
        cracks = ~np.isfinite(depth) & np.isfinite(eroded)
        depth[cracks] = eroded[cracks]
        depth[~np.isfinite(depth)] = np.nan
        return depth

    def _refine(self, depth: np.ndarray, T_ref_c: np.ndarray, K: np.ndarray) -> np.ndarray:
        """One fixed-point step: look the reference depth up where each pixel's ray meets it."""
        H, W = depth.shape
        v, u = np.mgrid[0:H, 0:W]
        rays = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3) @ np.linalg.inv(K).T
        points_ref = (rays * depth.reshape(-1, 1)) @ T_ref_c[:3, :3].T + T_ref_c[:3, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            pix = (points_ref @ K.T)[:, :2] / points_ref[:, 2:3]
        # Inverse depth is affine in the pixel on a plane, so bilinear lookups of it are exact there.
        inverse = cv2.remap(self._inverse_depth, np.nan_to_num(pix[:, 0], nan=-10).astype(np.float32).reshape(H, W),
                            np.nan_to_num(pix[:, 1], nan=-10).astype(np.float32).reshape(H, W),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).reshape(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            sampled = 1.0 / inverse.astype(np.float64)
        # Move along the pixel's ray so that the reference depth matches: solve z_ref(s) = sampled
        # with z_ref linear in the depth s along the ray: z_ref = a s + b.
        T_cr = T_ref_c
        a = rays @ T_cr[2, :3]
        b = T_cr[2, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            refined = (sampled - b) / a
        keep = np.isfinite(refined) & (refined > 0) & np.isfinite(depth.ravel())
        keep &= np.abs(refined - depth.ravel()) <= 0.05 * depth.ravel()
        return np.where(keep, refined, depth.ravel()).reshape(H, W)

    def __repr__(self) -> str:
        return f"RGBDScene({self.camera.width}x{self.camera.height})"
