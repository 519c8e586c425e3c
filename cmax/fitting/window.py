"""The typed, frozen input every stage of :func:`cmax.fit` reads: one window of events ready to warp.

Parameters are optimised in **pixels of displacement over the window** (a flow ``u`` as ``u T``, an
angular rate as ``omega T f``, an inverse depth as ``rho |v| T f``) and objectives are normalised by
their value for the unwarped events, so one set of solver tolerances fits every window.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from cmax.fitting.settings import LOW_PARALLAX_PX  # noqa: F401  (re-exported: the default of low_parallax_px)
from cmax.fitting.settings import max_events_for
from cmax.objectives import deformation, multi_reference_contrast
from cmax.warp import DepthGrid, WarpEvents, warp_se3

if TYPE_CHECKING:  # pragma: no cover
    from cmax.camera import Camera
    from cmax.events import Events
    from cmax.fitting.settings import FitSettings

__all__ = ["Window", "SE3Model", "SensorPixels", "LOW_PARALLAX_PX"]


@dataclass(frozen=True, eq=False)
class SensorPixels:
    """Where a window's events were recorded, for a fit through a lens: each event's sensor pixel ``pixels``
    (N, 2) [px], in the order of the window's (undistorted, integer) events, and the ``camera`` whose
    :meth:`~cmax.Camera.undistort_points` maps a sensor position to the fit's pinhole pixels (sub-pixel)."""

    pixels: np.ndarray
    camera: "Camera"


@dataclass(frozen=True, eq=False)
class Window:
    """One window of events prepared for the stages; read-only (the stages return new parameters).

    Attributes
    ----------
    ev : WarpEvents
        The (subsampled, dithered) events.
    settings : FitSettings
        With ``contrast`` and ``polarity_split`` resolved for the model.
    grid : DepthGrid
        The inverse-depth grid of se3.
    source : Events or None
        The events ``ev`` was made from (before subsampling and dither), so that a stage can draw other
        subsamples of the same window (:class:`cmax.fitting.pipeline.MotionMembersStage`); None when the
        window was built from prepared events.
    dt : Tensor (B, N)
        ``t - t_ref`` [s] for each reference time of ``settings.references``.
    dt_mid : Tensor (1, N)
        ``t - t_mid`` [s].
    focal : float
        Mean focal length [px].
    index, weight : Tensor (N, 4)
        Depth-grid nodes and bilinear weights of each event.
    cell : Tensor (N,)
        Depth-grid cell of each event.
    on : Tensor (N,) bool or None
        ON events when the contrast images polarities apart; None when merged.
    sensor : SensorPixels or None
        The sensor pixels of :attr:`source` and the camera through whose lens they were recorded: ``ev`` then
        holds each event dithered over its sensor pixel and mapped through the lens (unrounded), while
        :attr:`source` holds the nearest undistorted pixels; None for a pinhole.
    """

    ev: WarpEvents
    settings: "FitSettings"
    grid: DepthGrid
    source: "Events | None" = field(default=None, repr=False)
    sensor: SensorPixels | None = field(default=None, repr=False)
    dt: torch.Tensor = field(init=False)
    dt_mid: torch.Tensor = field(init=False)
    focal: float = field(init=False)
    index: torch.Tensor = field(init=False)
    weight: torch.Tensor = field(init=False)
    cell: torch.Tensor = field(init=False)
    on: torch.Tensor | None = field(init=False)
    _baselines: dict = field(init=False, repr=False)  # memo: contrast of the unwarped events per image scale

    def __post_init__(self) -> None:
        index, weight = self.grid.weights(self.ev.x, self.ev.y)
        values = dict(dt=self.ev.dt(self.settings.references), dt_mid=self.ev.dt((0.5,)),
                      focal=float(self.ev.K[0, 0] + self.ev.K[1, 1]) / 2, index=index, weight=weight,
                      cell=self.grid.cell_of(self.ev.x, self.ev.y),
                      on=(self.ev.polarity > 0) if self.settings.polarity_split else None, _baselines={})
        for name, value in values.items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_events(cls, events: "Events", K: np.ndarray, settings: "FitSettings",
                    depth_grid: tuple[int, int] = (24, 32), sensor: SensorPixels | None = None) -> "Window":
        """The window of ``events`` with intrinsics ``K`` (3, 3), subsampled and dithered as ``settings`` say;
        with ``sensor`` (the events' sensor pixels and lens), each event is dithered over its sensor pixel and
        mapped through the lens to ``K``'s pixels, unrounded. ``settings.max_events`` None: by the sensor
        (:func:`cmax.fitting.settings.max_events_for`)."""
        if settings.max_events is None:
            settings = replace(settings, max_events=max_events_for(None, events.width, events.height))
        if sensor is None:
            ev = WarpEvents.from_events(events, K, max_events=settings.max_events, seed=settings.seed)
        else:
            ev = WarpEvents.from_events(events, K, max_events=settings.max_events, seed=settings.seed,
                                        pixels=sensor.pixels, lens=sensor.camera.undistort_points)
        return cls(ev, settings, DepthGrid(tuple(depth_grid), events.width, events.height), events, sensor)

    def with_seed(self, seed: int) -> "Window":
        """The same window drawn again from :attr:`source` with another subsampling and dither ``seed``."""
        if self.source is None:
            raise ValueError("this window keeps no source events to draw again from (built from prepared events)")
        K = self.ev.K.double().numpy()
        return Window.from_events(self.source, K, replace(self.settings, seed=int(seed)), self.grid.shape,
                                  self.sensor)

    @property
    def T(self) -> float:
        """Duration [s]."""
        return self.ev.duration_s

    @property
    def omega_scale(self) -> float:
        """Pixels of displacement over the window per rad/s."""
        return self.T * self.focal

    def contrast(self, x: torch.Tensor, y: torch.Tensor, scale: int = 1) -> torch.Tensor:
        """Normalised multi-reference contrast of warped coordinates (B, N) at an image scale (1: unwarped)."""
        H, W = math.ceil(self.ev.height / scale), math.ceil(self.ev.width / scale)
        kind, sigma = self.settings.contrast or "variance", self.settings.sigma
        if scale not in self._baselines:
            x0, y0 = self.ev.x[None] / scale, self.ev.y[None] / scale
            self._baselines[scale] = multi_reference_contrast(
                x0, y0, height=H, width=W, sigma=sigma, kind=kind, on=self.on).detach()
        return multi_reference_contrast(x / scale, y / scale, height=H, width=W, sigma=sigma, kind=kind,
                                        baseline=self._baselines[scale], on=self.on)

    def scales(self) -> tuple[int, ...]:
        """Image scales of the coarse-to-fine schedule: ``settings.image_scales``, or by default 4, 2, 1 for
        sensors of 256 px and more, 2, 1 from 96 px, else 1."""
        if self.settings.image_scales is not None:
            return self.settings.image_scales
        size = max(self.ev.width, self.ev.height)
        return (4, 2, 1) if size >= 256 else (2, 1) if size >= 96 else (1,)


def _probe_lattice(w: Window):
    """The ``settings.collapse_lattice`` (rows, cols) of probe pixels over 10-90 % of the image, their rays,
    grid weights, and the probe times (T, 1) [s] (``settings.collapse_times`` times the duration)."""
    ev = w.ev
    rows, cols = w.settings.collapse_lattice
    ys, xs = torch.meshgrid(torch.linspace(0.1, 0.9, rows, dtype=ev.x.dtype) * ev.height,
                            torch.linspace(0.1, 0.9, cols, dtype=ev.x.dtype) * ev.width, indexing="ij")
    Kinv = torch.linalg.inv(ev.K)
    rays = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ Kinv.T
    index, weight = w.grid.weights(xs.reshape(-1), ys.reshape(-1))
    times = torch.tensor(w.settings.collapse_times, dtype=ev.x.dtype)[:, None] * w.T
    return xs, ys, rays.reshape(-1, 3), (index, weight), times


class SE3Model:
    """Parameter layout and the global motion objective of se3: ``x = (u (3), omega px (3), q (G or 1))``.

    ``u`` is the translation direction (``v = speed u / |u|``, or ``speed u`` with ``unit_norm`` False
    for solvers that hold ``|u| = 1`` as an equality constraint), ``q = rho * speed * T * f`` the inverse
    depth in pixels of parallax over the window. The objective is minus the normalised multi-reference
    contrast plus ``collapse_weight`` times the deformation guard (Shiba et al., Sensors 2022).
    """

    def __init__(self, w: Window, speed: float, *, unit_norm: bool = True) -> None:
        self.w, self.speed = w, speed
        self.omega_scale = w.omega_scale
        self.q_scale = speed * w.T * w.focal
        lo, hi = w.settings.depth_range
        self.q_bounds = (self.q_scale / hi, self.q_scale / lo)
        self.probes = _probe_lattice(w)
        self.unit_norm = unit_norm

    def velocity(self, u: torch.Tensor) -> torch.Tensor:
        if self.unit_norm:
            return self.speed * u / torch.sqrt((u * u).sum() + 1e-12)
        return self.speed * u

    def warp(self, v, omega, rho_events, dt):
        ev = self.w.ev
        return warp_se3(ev.rays, dt, v.to(ev.x.dtype), omega.to(ev.x.dtype), rho_events.to(ev.x.dtype), ev.K)

    def collapse(self, v, omega, rho_probes) -> torch.Tensor:
        xs, ys, rays, _, times = self.probes
        ev = self.w.ev
        x1, y1 = warp_se3(rays, times.expand(-1, rays.shape[0]), v.to(ev.x.dtype), omega.to(ev.x.dtype),
                          rho_probes.to(ev.x.dtype), ev.K)
        return deformation(xs, ys, x1.view(len(times), *xs.shape), y1.view(len(times), *xs.shape))

    def rho_events(self, q: torch.Tensor) -> torch.Tensor:
        if q.numel() == 1:
            return q.reshape(()).expand(len(self.w.ev)) / self.q_scale
        return DepthGrid.sample(q, self.w.index, self.w.weight) / self.q_scale

    def rho_probes(self, q: torch.Tensor) -> torch.Tensor:
        index, weight = self.probes[3]
        if q.numel() == 1:
            return q.reshape(()).expand(index.shape[0]) / self.q_scale
        return DepthGrid.sample(q, index, weight) / self.q_scale

    def objective(self, v: torch.Tensor, omega: torch.Tensor, rho_events: torch.Tensor,
                  rho_probes: torch.Tensor, scale: int = 1) -> torch.Tensor:
        """``-(normalised multi-reference contrast) + collapse_weight * deformation`` (lower is better)."""
        x, y = self.warp(v, omega, rho_events, self.w.dt)
        value = -self.w.contrast(x, y, scale)
        if self.w.settings.collapse_weight > 0:
            value = value + self.w.settings.collapse_weight * self.collapse(v, omega, rho_probes)
        return value

    def motion_loss(self, p: torch.Tensor, scale: int = 1, q_fixed: torch.Tensor | None = None) -> torch.Tensor:
        """The objective of parameters ``p = (u, omega px, q)``, or ``(u, omega px)`` with ``q_fixed``."""
        v = self.velocity(p[:3])
        omega = p[3:6] / self.omega_scale
        q = p[6:] if q_fixed is None else q_fixed
        return self.objective(v, omega, self.rho_events(q), self.rho_probes(q), scale)
