"""Preset synthetic scenes that resemble the paper's evaluation data (MVSEC and friends).

``make_scene(name, seed=0, width=346, height=260)`` builds one of
:data:`PRESETS`; every seed gives a different world and trajectory. The
camera resembles a DAVIS346 (fx about 226 px at 346 x 260, scaled with the
width; square pixels at any size: :func:`davis346_camera`). World frame: z up, metres. Each scene's :class:`SceneInfo` states its
depth and speed ranges over ``[0, duration_s]`` (checked by the tests), and
``scene.recommended_simulator`` gives :class:`cmax.sim.esim.EventSimulator`
keyword arguments that suit it.

==================  ===============================================  ============  ==============  =========
preset              world                                            depth [m]     speed [m/s]     |omega|
==================  ===============================================  ============  ==============  =========
``indoor_flying``   flying arena: floor mats, posters, boxes, plants  1.0 - 6.5     0 - 1.0         <= 30 deg/s
``driving_day``     street: road, sidewalks, facades, trees, cars    1.5 - 500     5 - 15          <= 12 deg/s
``driving_night``   the same at night: dark, low contrast, lit        1.5 - 500     5 - 15          <= 12 deg/s
                    windows, lamp pools; noisy sensor recommended
``hiking``          trail on rolling terrain, slopes, rocks, trees   0.5 - 200     0.6 - 1.8       <= 40 deg/s
``rotation``        closed office room, camera only rotates          0.8 - 6.0     0               <= 120 deg/s
``slider``          objects before a poster wall, linear slider      0.4 - 3.0     0.25 - 0.35     0
==================  ===============================================  ============  ==============  =========

The night preset recommends ``shot_noise_rate_hz=1.0``, ``leak_rate_hz=0.1``,
``threshold_sigma=0.05`` and thresholds 0.25 (noisier, less sensitive
pixels); the others ``threshold_sigma=0.03`` and thresholds 0.2.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from cmax.camera import Camera
from cmax.events import _check_sensor_size
from cmax.sim.textures import Texture, make_texture, night_version
from cmax.sim.trajectories import SinusoidalTrajectory, look_at_rotation
from cmax.sim.world import WorldBuilder

if TYPE_CHECKING:  # pragma: no cover
    from cmax.sim.scenes import PlanarScene

__all__ = ["PRESETS", "make_scene", "davis346_camera"]


def _scene_types():
    """``PlanarScene``, ``SceneInfo`` and ``Sky``, imported when a scene is built: the renderer
    imports torch, and the command line lists :data:`PRESETS` without it."""
    from cmax.sim.render import Sky
    from cmax.sim.scenes import PlanarScene, SceneInfo

    return PlanarScene, SceneInfo, Sky


_DAY_SIMULATOR = {"cp": 0.2, "cn": 0.2, "threshold_sigma": 0.03}
_NIGHT_SIMULATOR = {"cp": 0.25, "cn": 0.25, "threshold_sigma": 0.05,
                    "shot_noise_rate_hz": 1.0, "leak_rate_hz": 0.1}


def davis346_camera(width: int = 346, height: int = 260) -> Camera:
    """A DAVIS346-like pinhole (MVSEC's left camera, fx = 226.4 px at 346 x 260) for a ``width`` x ``height`` [px]
    sensor. A size of the DAVIS346's shape (346:260 to the pixel: ``height`` within 1 px of ``width * 260 / 346``)
    resamples it (:meth:`Camera.scaled`); any other shape keeps its square pixels and horizontal field of view: fx
    and fy both scale by ``width / 346``, the principal point stays at the same fraction of the image (a 640 x 360
    sensor sees the DAVIS346's width and less of its height; scaling each axis apart made fy / fx = 0.75 there)."""
    native = Camera.from_intrinsics(226.38, 226.15, 173.64, 133.73, 346, 260)
    if abs(round(width * 260 / 346) - height) <= 1:
        return native.scaled(width, height)
    sx, sy = width / 346, height / 260
    return Camera.from_intrinsics(226.38 * sx, 226.15 * sx, sx * (173.64 + 0.5) - 0.5, sy * (133.73 + 0.5) - 0.5,
                                  width, height)


def _limit_speeds(trajectory: SinusoidalTrajectory, duration_s: float, max_v: float, max_w: float,
                  min_v: float = 0.0) -> SinusoidalTrajectory:
    """Scale the oscillating parts so that min_v <= |v| <= max_v and |omega| <= max_w over the duration.

    The largest factor in [0, 1] that satisfies the bounds on 2001 samples is
    found by bisection (the drift alone must satisfy them).
    """
    t = np.linspace(0.0, duration_s, 2001)
    position_terms = trajectory.position_terms.copy()
    rotation_terms = trajectory.rotation_terms.copy()

    def scaled(k_v: float, k_w: float) -> SinusoidalTrajectory:
        p, r = position_terms.copy(), rotation_terms.copy()
        p[:, 1:4] *= k_v
        r[:, 1:4] *= k_w
        return SinusoidalTrajectory(trajectory.R0, trajectory.p0, trajectory.velocity, p, trajectory.rate, r)

    def fits(k_v: float, k_w: float) -> tuple[bool, bool]:
        xi = scaled(k_v, k_w).twist(t)
        speed = np.linalg.norm(xi[:, :3], axis=1)
        return (bool(speed.max() <= max_v and speed.min() >= min_v),
                bool(np.linalg.norm(xi[:, 3:], axis=1).max() <= max_w))

    k = [1.0, 1.0]
    for axis in (0, 1):
        if fits(*k)[axis]:
            continue
        lo, hi = 0.0, 1.0
        for _ in range(40):
            k[axis] = (lo + hi) / 2
            lo, hi = (k[axis], hi) if fits(*k)[axis] else (lo, k[axis])
        k[axis] = lo
    return scaled(*k)


def _room(b: WorldBuilder, size: tuple[float, float, float], wall: int, floor: int, ceiling: int) -> None:
    """Six faces of the box [0, Lx] x [0, Ly] x [0, Lz] (static shading by orientation)."""
    Lx, Ly, Lz = size
    b.quad([0, 0, 0], [Lx, 0, 0], [0, Ly, 0], floor, texels_per_metre=128.0, facing=[0, 0, 1])
    b.quad([0, 0, Lz], [Lx, 0, 0], [0, Ly, 0], ceiling, gain=0.75, facing=[0, 0, -1])
    b.quad([0, 0, 0], [Lx, 0, 0], [0, 0, Lz], wall, gain=0.95, facing=[0, 1, 0])
    b.quad([0, Ly, 0], [Lx, 0, 0], [0, 0, Lz], wall, gain=0.85, facing=[0, -1, 0])
    b.quad([0, 0, 0], [0, Ly, 0], [0, 0, Lz], wall, gain=0.8, facing=[1, 0, 0])
    b.quad([Lx, 0, 0], [0, Ly, 0], [0, 0, Lz], wall, gain=1.0, facing=[-1, 0, 0])


def _posters(b: WorldBuilder, rng: np.random.Generator, size: tuple[float, float, float], count: int,
             textures: list[int], walls: tuple[str, ...] = ("x1", "y0", "y1")) -> None:
    """Pictures hung 1 cm in front of the walls."""
    Lx, Ly, Lz = size
    for _ in range(count):
        w, h = rng.uniform(0.5, 1.6), rng.uniform(0.4, 1.2)
        z = rng.uniform(0.3, Lz - h - 0.2)
        wall = walls[rng.integers(len(walls))]
        tex = textures[rng.integers(len(textures))]
        if wall == "x1":
            y = rng.uniform(0.1, Ly - w - 0.1)
            b.image_quad([Lx - 0.01, y + w, z + h], [0, -w, 0], [0, 0, -h], tex, facing=[-1, 0, 0])
        elif wall == "x0":
            y = rng.uniform(0.1, Ly - w - 0.1)
            b.image_quad([0.01, y, z + h], [0, w, 0], [0, 0, -h], tex, facing=[1, 0, 0])
        elif wall == "y0":
            x = rng.uniform(0.1, Lx - w - 0.1)
            b.image_quad([x, 0.01, z + h], [w, 0, 0], [0, 0, -h], tex, facing=[0, 1, 0])
        else:
            x = rng.uniform(0.1, Lx - w - 0.1)
            b.image_quad([x + w, Ly - 0.01, z + h], [-w, 0, 0], [0, 0, -h], tex, facing=[0, -1, 0])


# -- presets ------------------------------------------------------------------------------
def _indoor_flying(rng: np.random.Generator, camera: Camera, duration_s: float, size: int) -> PlanarScene:
    PlanarScene, SceneInfo, Sky = _scene_types()
    b = WorldBuilder(rng, size)
    room = (6.4, 6.0, 3.0)
    Lx, Ly, Lz = room
    wall, mat, ceiling = b.texture("plaster"), b.texture("mat"), b.texture("plaster")
    posters = [b.texture("poster") for _ in range(3)]
    boxes = [b.texture(kind) for kind in ("rock", "wood", "poster", "car")]
    foliage, bark = b.texture("foliage"), b.texture("bark")
    _room(b, room, wall, mat, ceiling)
    _posters(b, rng, room, int(rng.integers(5, 9)), posters)
    for _ in range(int(rng.integers(7, 12))):  # boxes and crates on the floor, some stacked
        s = rng.uniform([0.3, 0.3, 0.3], [1.1, 1.1, 1.2])
        x, y = rng.uniform(2.6, Lx - 0.6), rng.uniform(0.5, Ly - 0.5)
        b.box([x, y, s[2] / 2], s, rng.uniform(0, np.pi), boxes[rng.integers(len(boxes))])
        if rng.random() < 0.3:
            t = s * rng.uniform(0.4, 0.8, 3)
            b.box([x, y, s[2] + t[2] / 2], t, rng.uniform(0, np.pi), boxes[rng.integers(len(boxes))])
    for _ in range(2):  # pillars / tripods
        b.box([rng.uniform(3.0, Lx - 0.4), rng.uniform(0.4, Ly - 0.4), 1.2], [0.12, 0.12, 2.4], rng.uniform(0, 1), bark)
    for _ in range(int(rng.integers(1, 4))):  # potted plants near the walls
        x = rng.uniform(3.5, Lx - 0.5)
        y = rng.choice([0.4, Ly - 0.4])
        b.tree([x, y, 0.0], height=rng.uniform(1.2, 2.0), crown_radius=rng.uniform(0.35, 0.6),
               trunk_texture=bark, crown_texture=foliage, facing_yaw=np.pi / 2)
    R0 = look_at_rotation([1.0, 0.0, 0.0])
    trajectory = SinusoidalTrajectory.random(
        rng, R0=R0, p0=[0.95, Ly / 2 + rng.uniform(-0.3, 0.3), 1.3 + rng.uniform(-0.1, 0.1)],
        position_amplitude=[0.3, 0.6, 0.25], rotation_amplitude=np.deg2rad([6.0, 14.0, 4.0]),
        frequencies=(0.08, 0.35), terms=3,
    )
    trajectory = _limit_speeds(trajectory, duration_s, 1.0, np.deg2rad(30.0))
    info = SceneInfo("indoor_flying", duration_s, (1.0, 6.5), (0.0, 1.0), 30.0,
                     "A drone in a flying arena (like MVSEC indoor_flying): floor mats, posters, boxes.")
    return PlanarScene(b.build(), camera, trajectory, sky=Sky(60, 60, 60), info=info,
                       recommended_simulator=_DAY_SIMULATOR, texture_size=size)


def _street(b: WorldBuilder, rng: np.random.Generator, length: float, night: bool) -> None:
    """Road along +x from x = -30 to ``length``: sidewalks, facades, trees, parked cars, lamps."""
    def texture(kind: str, lit: float = 0.0) -> Texture:
        made = make_texture(kind, int(rng.integers(1 << 31)), b.texture_size)
        return night_version(made, rng, lit_fraction=lit) if night else made

    def tex(kind: str, lit: float = 0.0) -> int:
        return b.texture(texture(kind, lit))

    asphalt = texture("asphalt")
    if night:  # pools of lamp light every 16 m, baked into the road texture (one texture period)
        s = asphalt.size
        x = (np.arange(s) + 0.5) / s
        pool = np.exp(-0.5 * ((x - 0.5) / 0.12) ** 2)[None, :] * np.linspace(0.6, 1.0, s)[:, None]
        asphalt = Texture(np.clip(asphalt.values * (1 + 5 * pool), 0, 255), name=asphalt.name)
    road = b.texture(asphalt)
    pavement, kerb = tex("rock"), tex("rock")
    facades = [tex("facade", 0.35) for _ in range(4)]
    walls = [tex("plaster") for _ in range(2)]
    crowns = [tex("foliage") for _ in range(3)]
    bark = tex("bark")
    cars = [tex("car") for _ in range(4)]
    x0, half = -30.0, 5.5
    span = length - x0
    # Road: 16 m per texture period along x, 11 m across (the texture's y).
    size = b.texture_size
    b.quad([x0, half, 0], [span, 0, 0], [0, -2 * half, 0], road,
           texel_map=np.array([[span / 16.0 * size, 0, 0], [0, size, 0]]), gain=1.0, facing=[0, 0, 1])
    for side in (1.0, -1.0):
        y_kerb = side * half
        b.quad([x0, y_kerb, 0], [span, 0, 0], [0, 0, 0.15], kerb, texels_per_metre=128.0, gain=0.8,
               facing=[0, -side, 0])
        b.quad([x0, y_kerb, 0.15], [span, 0, 0], [0, side * 3.0, 0], pavement, texels_per_metre=96.0,
               facing=[0, 0, 1])
        x = x0
        setback_prev = None
        while x < length:  # buildings of random widths, heights and setbacks
            w = rng.uniform(8, 25)
            setback = side * rng.uniform(8.5, 12.0)
            height = rng.uniform(6, 22)
            texture = facades[rng.integers(len(facades))] if rng.random() < 0.8 else walls[rng.integers(2)]
            b.quad([x, setback, 0.15], [w, 0, 0], [0, 0, height], texture, texels_per_metre=48.0,
                   gain=rng.uniform(0.75, 1.1), facing=[0, -side, 0])
            b.quad([x, side * half + side * 3.0, 0.15], [w, 0, 0], [0, setback - side * (half + 3.0), 0],
                   pavement, texels_per_metre=96.0, gain=0.9, facing=[0, 0, 1])
            if setback_prev is not None:  # side wall joining the two setbacks
                b.quad([x, setback_prev, 0.15], [0, setback - setback_prev, 0], [0, 0, height], walls[0],
                       texels_per_metre=48.0, gain=0.7)
            setback_prev = setback
            x += w
        x = x0 + rng.uniform(0, 6)
        while x < length:  # trees on the pavement
            b.tree([x, side * (half + 1.8), 0.15], height=rng.uniform(4.5, 8.0), crown_radius=rng.uniform(1.4, 2.4),
                   trunk_texture=bark, crown_texture=crowns[rng.integers(3)], facing_yaw=0.0)
            x += rng.uniform(7, 16)
        x = x0 + rng.uniform(0, 5)
        while x < length:  # parked cars (boxes) in the parking lane
            if rng.random() < 0.65:
                b.box([x, side * 4.4, 0.75], [4.3, 1.8, 1.45], rng.normal(0, 0.03), (cars[rng.integers(4)], kerb),
                      texels_per_metre=110.0, fit_sides=True)
            x += rng.uniform(5.0, 7.5)
        for x in np.arange(x0 + 8.0, length, 16.0):  # lamp posts
            b.box([x, side * (half + 0.4), 3.15], [0.16, 0.16, 6.0], 0.0, bark, texels_per_metre=200.0, gains=(0.6, 0.5, 0.4))
    # The street ends at a row of houses across it.
    b.quad([length, -40, 0], [0, 80, 0], [0, 0, 18], facades[0], texels_per_metre=48.0, facing=[-1, 0, 0])


def _driving(rng: np.random.Generator, camera: Camera, duration_s: float, size: int, night: bool) -> PlanarScene:
    PlanarScene, SceneInfo, Sky = _scene_types()
    b = WorldBuilder(rng, size)
    speed = rng.uniform(8.0, 12.0)
    length = speed * duration_s + 40.0 + rng.uniform(100, 250)
    _street(b, rng, length, night)
    R0 = look_at_rotation([1.0, 0.0, 0.0])
    trajectory = SinusoidalTrajectory.random(
        rng, R0=R0, p0=[0.0, -1.75 + rng.uniform(-0.2, 0.2), 1.45], velocity=[speed, 0, 0],
        position_amplitude=[6.0, 0.35, 0.03], rotation_amplitude=np.deg2rad([1.0, 2.5, 0.6]),
        frequencies=(0.05, 0.3), terms=3,
    )
    trajectory = _limit_speeds(trajectory, duration_s, 14.5, np.deg2rad(12.0), min_v=5.5)
    name = "driving_night" if night else "driving_day"
    description = ("Forward driving down a street at night: dark, low contrast, lit windows and lamp pools."
                   if night else "Forward driving down a street by day: facades, trees, parked cars.")
    info = SceneInfo(name, duration_s, (1.5, 500.0), (5.0, 15.0), 12.0, description)
    sky = Sky(zenith=6.0, horizon=14.0, ground=5.0) if night else Sky(zenith=185.0, horizon=235.0, ground=90.0)
    return PlanarScene(b.build(), camera, trajectory, sky=sky, info=info,
                       recommended_simulator=_NIGHT_SIMULATOR if night else _DAY_SIMULATOR, texture_size=size)


def _hiking(rng: np.random.Generator, camera: Camera, duration_s: float, size: int) -> PlanarScene:
    PlanarScene, SceneInfo, Sky = _scene_types()
    b = WorldBuilder(rng, size)
    speed = rng.uniform(0.9, 1.3)
    length = speed * duration_s + 150.0
    trail, slope, rock, bark = b.texture("ground"), b.texture("ground"), b.texture("rock"), b.texture("bark")
    crowns = [b.texture("foliage") for _ in range(3)]
    # Height profile h(x) = sum a_k sin(2 pi x / lambda_k + phi_k); the camera follows it exactly.
    wavelengths = rng.uniform(15, 60, 3)
    amplitudes = rng.uniform(0.3, 1.2, 3) * wavelengths / 60.0
    phases = rng.uniform(0, 2 * np.pi, 3)

    def height(x):
        x = np.asarray(x, float)
        return (amplitudes * np.sin(2 * np.pi * x[..., None] / wavelengths + phases)).sum(-1)

    half = 1.2
    xs = np.arange(-20.0, length + 1e-9, 1.0)
    hs = height(xs)
    angles = {1.0: np.deg2rad(rng.uniform(12, 28)), -1.0: np.deg2rad(rng.uniform(5, 20))}
    size_t = b.texture_size
    for x_a, x_b, h_a, h_b in zip(xs[:-1], xs[1:], hs[:-1], hs[1:]):
        edge = np.array([x_b - x_a, 0.0, h_b - h_a])
        # Texture coordinates follow world (x, y) so neighbouring strips join without a seam.
        tm = np.array([[edge[0] * 64.0, 0, x_a * 64.0 % size_t], [0, 2 * half * 64.0, 0]])
        b.quad([x_a, -half, h_a], edge, [0, 2 * half, 0], trail, texel_map=tm, facing=[0, 0, 1])
        for side, angle in angles.items():
            out = 40.0 * np.array([0.0, side * np.cos(angle), np.sin(angle)])
            tm = np.array([[edge[0] * 48.0, 0, x_a * 48.0 % size_t], [0, 40.0 * 48.0, 0]])
            b.quad([x_a, side * half, h_a], edge, out, slope, texel_map=tm, gain=0.9 if side > 0 else 0.8,
                   facing=[0, 0, 1])

    def ground(x, y):
        side = np.sign(y)
        d = max(abs(y) - half, 0.0)
        return float(height(x)) + d * np.tan(angles[side])

    for _ in range(int(length / 2.5)):  # rocks beside the trail
        x = rng.uniform(-10, length)
        y = rng.choice([-1, 1]) * rng.uniform(half + 0.3, 6.0)
        s = rng.uniform(0.2, 0.9, 3)
        b.box([x, y, ground(x, y) + s[2] * 0.3], s, rng.uniform(0, np.pi), rock, texels_per_metre=160.0)
    for _ in range(int(length / 3.0)):  # trees on the slopes
        x = rng.uniform(-10, length)
        y = rng.choice([-1, 1]) * rng.uniform(half + 2.0, 25.0)
        b.tree([x, y, ground(x, y)], height=rng.uniform(4, 12), crown_radius=rng.uniform(1.2, 3.0),
               trunk_texture=bark, crown_texture=crowns[rng.integers(3)], facing_yaw=0.0)
    for _ in range(int(length / 2.0)):  # bushes close to the trail
        x = rng.uniform(-10, length)
        y = rng.choice([-1, 1]) * rng.uniform(half + 0.4, 4.0)
        r = rng.uniform(0.3, 0.7)
        base = np.array([x, y, ground(x, y) + 2 * r])
        b.image_quad(base - [r, 0, 0], [2 * r, 0, 0], [0, 0, -2 * r], crowns[rng.integers(3)], gain=0.8)
    R0 = look_at_rotation([1.0, 0.0, -0.12])
    eye = 1.65
    # z(t) = h(speed * t) + eye + bob: the profile's sinusoids become sinusoids in time.
    terrain_terms = np.column_stack([
        speed / wavelengths, np.zeros(3), np.zeros(3), amplitudes,
        np.zeros(3), np.zeros(3), phases,
    ])
    bob = np.array([[1.8, 0.0, 0.0, 0.02, 0.0, 0.0, 0.0], [0.9, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0]])
    sway = SinusoidalTrajectory.random(rng, R0=R0, p0=[0.0, 0.0, eye], velocity=[speed, 0, 0],
                                       position_amplitude=[0.0, 0.25, 0.0],
                                       rotation_amplitude=np.deg2rad([8.0, 22.0, 2.0]), frequencies=(0.05, 0.25))
    trajectory = SinusoidalTrajectory(R0, sway.p0, sway.velocity,
                                      np.concatenate([sway.position_terms, terrain_terms, bob]),
                                      sway.rate, sway.rotation_terms)
    trajectory = _limit_speeds(trajectory, duration_s, 1.8, np.deg2rad(40.0), min_v=0.6)
    info = SceneInfo("hiking", duration_s, (0.5, 200.0), (0.6, 1.8), 40.0,
                     "Walking along a trail over rolling terrain, with rocks, bushes and trees.")
    return PlanarScene(b.build(), camera, trajectory, sky=Sky(zenith=170.0, horizon=225.0, ground=110.0),
                       info=info, recommended_simulator=_DAY_SIMULATOR, texture_size=size)


def _office(b: WorldBuilder, rng: np.random.Generator, room: tuple[float, float, float]) -> None:
    Lx, Ly, Lz = room
    wall, floor, ceiling = b.texture("plaster"), b.texture("wood"), b.texture("plaster")
    posters = [b.texture("poster") for _ in range(4)]
    boxes = [b.texture(k) for k in ("rock", "wood", "car")]
    _room(b, room, wall, floor, ceiling)
    _posters(b, rng, room, int(rng.integers(8, 13)), posters, walls=("x0", "x1", "y0", "y1"))
    for _ in range(int(rng.integers(5, 9))):
        s = rng.uniform([0.3, 0.3, 0.3], [0.9, 0.9, 1.1])
        # Boxes along the walls keep at least 0.8 m from the camera at the centre.
        side = rng.integers(4)
        along = rng.uniform(0.6, 1.0 - 0.6 / max(Lx, Ly))
        x, y = [(along * Lx, 0.6), (along * Lx, Ly - 0.6), (0.6, along * Ly), (Lx - 0.6, along * Ly)][side]
        b.box([x, y, s[2] / 2], s, rng.uniform(0, np.pi), boxes[rng.integers(3)])


def _rotation(rng: np.random.Generator, camera: Camera, duration_s: float, size: int) -> PlanarScene:
    PlanarScene, SceneInfo, Sky = _scene_types()
    b = WorldBuilder(rng, size)
    room = (rng.uniform(4.5, 5.5), rng.uniform(4.0, 5.0), 2.8)
    _office(b, rng, room)
    R0 = look_at_rotation([np.cos(rng.uniform(0, 2 * np.pi)), np.sin(rng.uniform(0, 2 * np.pi)), 0.0])
    trajectory = SinusoidalTrajectory.random(
        rng, R0=R0, p0=[room[0] / 2, room[1] / 2, 1.4], rotation_amplitude=np.deg2rad([20.0, 40.0, 25.0]),
        frequencies=(0.1, 0.6), terms=3,
    )
    trajectory = _limit_speeds(trajectory, duration_s, 0.0, np.deg2rad(120.0))
    info = SceneInfo("rotation", duration_s, (0.8, 6.0), (0.0, 0.0), 120.0,
                     "A camera rotating in place in an office with posters (like ECD *_rotation).")
    return PlanarScene(b.build(), camera, trajectory, sky=Sky(60, 60, 60), info=info,
                       recommended_simulator=_DAY_SIMULATOR, texture_size=size)


def _slider(rng: np.random.Generator, camera: Camera, duration_s: float, size: int) -> PlanarScene:
    PlanarScene, SceneInfo, Sky = _scene_types()
    b = WorldBuilder(rng, size)
    speed = rng.uniform(0.25, 0.35)
    travel = speed * duration_s
    wall_x = rng.uniform(2.3, 2.9)
    poster, table = b.texture("poster"), b.texture("wood")
    objects = [b.texture(k) for k in ("rock", "car", "poster", "wood")]
    foliage, bark = b.texture("foliage"), b.texture("bark")
    y_min, y_max = -travel - 3.0, 3.0
    b.quad([wall_x, y_max, 2.0], [0, y_min - y_max, 0], [0, 0, -2.8], poster, texels_per_metre=160.0,
           facing=[-1, 0, 0])
    b.quad([-1.0, y_max, -0.8], [wall_x + 1.0, 0, 0], [0, y_min - y_max, 0], table, texels_per_metre=128.0,
           facing=[0, 0, 1])
    for _ in range(int(4 + 3 * travel)):  # objects on the table at several depths
        s = rng.uniform([0.1, 0.1, 0.15], [0.35, 0.35, 0.6])
        x = rng.uniform(0.65, wall_x - 0.25)
        y = rng.uniform(y_min + 1.0, y_max - 1.0)
        b.box([x, y, -0.8 + s[2] / 2], s, rng.uniform(0, np.pi), objects[rng.integers(4)], texels_per_metre=256.0)
    for _ in range(2):
        x, y = rng.uniform(1.2, wall_x - 0.4), rng.uniform(y_min + 1, y_max - 1)
        b.tree([x, y, -0.8], height=rng.uniform(0.8, 1.3), crown_radius=rng.uniform(0.2, 0.35),
               trunk_texture=bark, crown_texture=foliage, facing_yaw=np.pi / 2)
    R0 = look_at_rotation([1.0, 0.0, -0.25])
    # Camera x (right) is world -y: the slider moves the camera to its right.
    trajectory = SinusoidalTrajectory(R0=R0, p0=[0.0, 0.0, 0.0], velocity=[0.0, -speed, 0.0])
    info = SceneInfo("slider", duration_s, (0.4, 3.0), (0.25, 0.35), 0.0,
                     "A camera on a linear slider before objects and a poster wall (like ECD slider_depth).")
    return PlanarScene(b.build(), camera, trajectory, sky=Sky(40, 40, 40), info=info,
                       recommended_simulator=_DAY_SIMULATOR, texture_size=size)


PRESETS: dict[str, Callable[..., PlanarScene]] = {
    "indoor_flying": _indoor_flying,
    "driving_day": lambda rng, camera, duration, size: _driving(rng, camera, duration, size, night=False),
    "driving_night": lambda rng, camera, duration, size: _driving(rng, camera, duration, size, night=True),
    "hiking": _hiking,
    "rotation": _rotation,
    "slider": _slider,
}


#: The smallest image side [px] of a preset scene (:func:`make_scene`): its images' gradients need two pixels a side.
MIN_SCENE_SIZE = 2


def make_scene(name: str, seed: int = 0, width: int = 346, height: int = 260, *,
               duration_s: float = 10.0, texture_size: int = 512) -> PlanarScene:
    """One of the preset scenes (:data:`PRESETS`), different for every ``seed``.

    Parameters
    ----------
    name : str
        ``indoor_flying``, ``driving_day``, ``driving_night``, ``hiking``,
        ``rotation`` or ``slider`` (see the module docstring for their ranges).
    seed : int
        Seed of the world, its textures and the trajectory (>= 0).
    width, height : int
        Image size [px], at least :data:`MIN_SCENE_SIZE` (2) each; the intrinsics are a DAVIS346's scaled to it
        (square pixels at any shape: :func:`davis346_camera`).
    duration_s : float
        Length of the trajectory the world is built for [s]; the stated
        ranges hold on ``[0, duration_s]``.
    texture_size : int
        Side of the procedural textures (a power of two; 256 builds faster).

    Returns
    -------
    PlanarScene
        With ``scene.info`` (a :class:`SceneInfo`) and ``scene.recommended_simulator``.

    Examples
    --------
    >>> import numpy as np
    >>> scene = make_scene("slider", seed=1, width=64, height=48, texture_size=64)
    >>> intensity, depth = scene.render(0.5)
    >>> intensity.shape, intensity.dtype.name, bool(np.nanmax(depth) <= 3.0)
    ((48, 64), 'float32', True)
    """
    if name not in PRESETS:
        raise ValueError(f"name must be one of {sorted(PRESETS)}, got {name!r}")
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if not (isinstance(duration_s, (int, float, np.integer, np.floating)) and 0 < duration_s <= 600):
        raise ValueError(f"duration_s must be in (0, 600] seconds, got {duration_s!r}")
    width, height = _check_sensor_size(width, height)
    if min(width, height) < MIN_SCENE_SIZE:
        raise ValueError(f"width and height must be at least {MIN_SCENE_SIZE} pixels (the scene's images are "
                         f"differentiated across both axes), got {width}x{height}")
    camera = davis346_camera(width, height)
    rng = np.random.default_rng([int(seed), sorted(PRESETS).index(name)])
    return PRESETS[name](rng, camera, float(duration_s), int(texture_size))
