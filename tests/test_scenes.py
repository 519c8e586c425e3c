"""Tests of the synthetic scenes: exact depth, consistent poses and twists, preset ranges, files."""
from __future__ import annotations

import numpy as np
import pytest

from cmax.camera import Camera
from cmax.geometry import invert_pose, relative_pose, se3_exp, vee
from cmax.sim.presets import PRESETS, davis346_camera, make_scene
from cmax.sim.render import PlanarRenderer
from cmax.sim.scenes import PlanarScene, RGBDScene, warp_image
from cmax.sim.textures import Texture, TextureAtlas, make_texture
from cmax.sim.trajectories import SinusoidalTrajectory, look_at_rotation
from cmax.sim.world import WorldBuilder

W, H = 173, 130  # half a DAVIS346: fast, still detailed


@pytest.fixture(scope="module")
def scenes() -> dict[str, PlanarScene]:
    return {name: make_scene(name, seed=0, width=W, height=H, texture_size=256) for name in PRESETS}


def _single_plane_scene(distance: float, width: int = 40, height: int = 30) -> PlanarScene:
    b = WorldBuilder(np.random.default_rng(0), 64)
    tex = b.texture("poster")
    b.quad([distance, 50.0, 50.0], [0.0, -100.0, 0.0], [0.0, 0.0, -100.0], tex)
    R0 = look_at_rotation([1.0, 0.0, 0.0])
    trajectory = SinusoidalTrajectory(R0=R0, p0=[0.0, 0.0, 0.0], velocity=[0.5, 0.0, 0.0])
    camera = Camera.from_intrinsics(30.0, 30.0, 19.5, 14.5, width, height)
    return PlanarScene(b.build(), camera, trajectory, texture_size=64)


# -- geometry of the renderer ------------------------------------------------------------------
def test_fronto_parallel_plane_depth_is_its_distance():
    scene = _single_plane_scene(3.0)
    intensity, depth = scene.render(0.0)
    assert intensity.shape == depth.shape == (30, 40)
    assert intensity.dtype == depth.dtype == np.float32
    np.testing.assert_allclose(depth, 3.0, rtol=1e-6)
    _, depth = scene.render(1.0)  # moved 0.5 m towards the plane
    np.testing.assert_allclose(depth, 2.5, rtol=1e-6)
    assert 0 <= intensity.min() and intensity.max() <= 255


def test_tilted_plane_depth_matches_closed_form():
    # Floor z = 0 seen from height h looking along +x: depth of row v is h * fy / (v - cy) below the horizon.
    b = WorldBuilder(np.random.default_rng(0), 64)
    b.quad([-1.0, 100.0, 0.0], [200.0, 0.0, 0.0], [0.0, -200.0, 0.0], b.texture("ground"))
    camera = Camera.from_intrinsics(30.0, 30.0, 19.5, 14.5, 40, 30)
    T = np.eye(4)
    T[:3, :3] = look_at_rotation([1.0, 0.0, 0.0])
    T[:3, 3] = [0.0, 0.0, 1.5]
    _, depth = PlanarRenderer(b.build(), camera, texture_size=64).render(T)
    rows = np.arange(30)
    expected = np.where(rows > 14.5, 1.5 * 30.0 / np.maximum(rows - 14.5, 1e-9), np.nan)
    below = rows > 15
    np.testing.assert_allclose(depth[below], np.broadcast_to(expected[below, None], (below.sum(), 40)), rtol=1e-5)
    assert np.isnan(depth[rows < 14]).all()  # sky above the horizon


def _brute_force_depth(renderer: PlanarRenderer, T_w_c: np.ndarray) -> np.ndarray:
    """All parallelograms against all pixels in float64, alpha-tested, nearest wins."""
    world, camera, atlas = renderer.world, renderer.camera, renderer.atlas
    v, u = np.mgrid[0: camera.height, 0: camera.width]
    rays_c = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(camera.K).T
    rays_w = rays_c @ T_w_c[:3, :3].T
    centre = T_w_c[:3, 3]
    best = np.full(len(rays_c), np.inf)
    S = atlas.size
    for r in range(len(world)):
        o, a, b = world.origins[r], world.edges_u[r], world.edges_v[r]
        n = np.cross(a, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (n @ (o - centre)) / (rays_w @ n)
        point = centre + z[:, None] * rays_w - o
        G = np.array([[a @ a, a @ b], [a @ b, b @ b]])
        s, t = np.linalg.solve(G, np.stack([point @ a, point @ b])).reshape(2, -1)
        hit = (z > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
        if world.cutout[r]:
            texel = world.texel_maps[r] @ np.stack([s, t, np.ones_like(s)])
            x, y = (np.floor(np.nan_to_num(texel)).astype(np.int64) & (S - 1))
            hit &= atlas.alpha[world.texture_ids[r] * S * S + y * S + x]
        best = np.where(hit & (z < best), z, best)
    return np.where(np.isfinite(best), best, np.nan).reshape(camera.height, camera.width)


@pytest.mark.parametrize("name", ["indoor_flying", "driving_day", "hiking"])
def test_tiled_renderer_agrees_with_brute_force(name):
    scene = make_scene(name, seed=1, width=64, height=48, texture_size=64)
    for t in (0.5, 4.0):
        T = scene.pose(t)
        _, depth = scene.render_pose(T)
        reference = _brute_force_depth(scene.renderer, T)
        both = np.isfinite(depth) & np.isfinite(reference)
        same_coverage = np.isfinite(depth) == np.isfinite(reference)
        assert same_coverage.mean() > 0.995
        close = np.abs(depth[both] - reference[both]) <= 1e-4 * reference[both]
        assert close.mean() > 0.99  # boundary pixels may go either way in float32


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_warping_with_ground_truth_reproduces_the_next_render(scenes, name):
    """Depth and poses are right: the render at t warped into t+dt matches the render at t+dt."""
    from cmax.sim.synthetic import motion_field

    scene = scenes[name]
    K = scene.camera.K
    for t in (2.0, 6.0):
        image_a, depth_a = scene.render(t)
        du, dv = motion_field(depth_a, scene.twist(t), K)
        dt = 3.0 / float(np.median(np.hypot(du, dv)))  # about 3 pixels of motion
        image_b, depth_b = scene.render(t + dt)
        T_a_b = relative_pose(scene.pose(t), scene.pose(t + dt))
        warped, valid = warp_image(image_a, depth_b, T_a_b, K, depth_a=depth_a)
        assert valid.mean() > 0.5
        error = np.abs(warped - image_b)[valid]
        unwarped = np.abs(image_a - image_b)[valid]
        # A 0.57 degree error of the relative rotation is clearly visible.
        wrong, wrong_valid = warp_image(image_a, depth_b, T_a_b @ se3_exp([0, 0, 0, 0, 0.01, 0]), K, depth_a=depth_a)
        wrong_error = np.abs(wrong - image_b)[wrong_valid]
        assert error.mean() < 0.3 * unwarped.mean(), (error.mean(), unwarped.mean())
        assert error.mean() < 0.6 * wrong_error.mean(), (error.mean(), wrong_error.mean())
        assert np.median(error) < 2.5


# -- trajectories -----------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_twist_integration_reproduces_pose_change(scenes, name):
    scene = scenes[name]
    t0, t1, steps = 1.0, 1.5, 2000
    T = scene.pose(t0)
    dt = (t1 - t0) / steps
    for k in range(steps):  # midpoint rule
        T = T @ se3_exp(scene.twist(t0 + (k + 0.5) * dt) * dt)
    expected = scene.pose(t1)
    np.testing.assert_allclose(T[:3, :3], expected[:3, :3], atol=1e-6)
    np.testing.assert_allclose(T[:3, 3], expected[:3, 3], atol=1e-6 * max(1.0, np.linalg.norm(expected[:3, 3])))


def test_twist_is_the_pose_derivative():
    rng = np.random.default_rng(3)
    trajectory = SinusoidalTrajectory.random(
        rng, R0=look_at_rotation([1.0, 0.2, 0.1]), p0=[1, 2, 3], velocity=[0.3, 0.0, 0.1],
        position_amplitude=[0.5, 0.3, 0.2], rotation_amplitude=[0.4, 0.6, 0.3], frequencies=(0.2, 1.0),
    )
    for t in (0.0, 0.7, 3.3):
        h = 1e-6
        derivative = (trajectory.pose(t + h) - trajectory.pose(t - h)) / (2 * h)
        xi_numeric = vee(invert_pose(trajectory.pose(t)) @ derivative)
        np.testing.assert_allclose(trajectory.twist(t), xi_numeric, atol=1e-6)
    assert trajectory.pose(np.array([0.0, 1.0])).shape == (2, 4, 4)
    assert trajectory.twist(np.array([0.0, 1.0])).shape == (2, 6)


# -- presets --------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_preset_depth_and_speed_within_stated_ranges(name):
    scene = make_scene(name, seed=2, width=87, height=65, texture_size=64)
    info = scene.info
    assert info.name == name and info.duration_s == 10.0
    lo, hi = np.inf, -np.inf
    for t in np.linspace(0.0, info.duration_s, 21):
        _, depth = scene.render(float(t))
        assert np.isfinite(depth).mean() > 0.3
        lo, hi = min(lo, np.nanmin(depth)), max(hi, np.nanmax(depth))
    assert info.depth_range_m[0] <= lo and hi <= info.depth_range_m[1], (lo, hi)
    xi = np.stack([scene.twist(float(t)) for t in np.linspace(0.0, info.duration_s, 501)])
    speed = np.linalg.norm(xi[:, :3], axis=1)
    assert info.speed_range_mps[0] - 1e-9 <= speed.min() and speed.max() <= info.speed_range_mps[1] + 1e-9
    assert np.rad2deg(np.linalg.norm(xi[:, 3:], axis=1)).max() <= info.max_angular_speed_dps + 1e-6
    if name.startswith("driving"):
        assert hi > 30.0  # depth to 30 m and beyond
    if name == "rotation":
        assert speed.max() == 0.0
    if name == "slider":
        assert np.allclose(xi[:, 3:], 0.0) and np.allclose(xi[:, 1:3], 0.0)  # pure translation along x


def test_presets_differ_per_seed_and_repeat_per_seed():
    a = make_scene("indoor_flying", seed=0, width=64, height=48, texture_size=64).render(1.0)[0]
    b = make_scene("indoor_flying", seed=1, width=64, height=48, texture_size=64).render(1.0)[0]
    c = make_scene("indoor_flying", seed=0, width=64, height=48, texture_size=64).render(1.0)[0]
    assert np.abs(a - b).mean() > 5.0
    np.testing.assert_array_equal(a, c)


def test_night_is_darker_with_less_contrast_and_noisier_sensor():
    day = make_scene("driving_day", seed=0, width=87, height=65, texture_size=64)
    night = make_scene("driving_night", seed=0, width=87, height=65, texture_size=64)
    d, n = day.render(1.0)[0], night.render(1.0)[0]
    assert n.mean() < 0.4 * d.mean()
    assert n.std() < d.std()
    assert night.recommended_simulator["shot_noise_rate_hz"] > 0
    assert "shot_noise_rate_hz" not in day.recommended_simulator


def test_davis346_intrinsics_scale_with_size():
    assert abs(davis346_camera().fx - 226.38) < 1e-9
    assert abs(davis346_camera(173, 130).fx - 113.19) < 1e-9


@pytest.mark.parametrize("width, height", [(640, 360), (128, 128), (346, 100), (200, 400)])
def test_a_scene_of_another_shape_than_the_davis346_keeps_square_pixels(width, height):
    # (was: each axis scaled apart: 640x360 gave fx 418.7, fy 313.1, pixels 1.34 times wider than tall, unsaid)
    camera, native = davis346_camera(width, height), davis346_camera()
    assert camera.fx / camera.fy == pytest.approx(native.fx / native.fy, rel=1e-12)
    assert camera.fx == pytest.approx(native.fx * width / 346, rel=1e-12)      # the horizontal field of view kept
    assert (camera.cx + 0.5) / width == pytest.approx((native.cx + 0.5) / 346, rel=1e-12)
    assert (camera.cy + 0.5) / height == pytest.approx((native.cy + 0.5) / 260, rel=1e-12)
    scene = make_scene("slider", width=width, height=height, texture_size=16, duration_s=1.0)
    assert np.allclose(scene.camera.K, camera.K)
    # a size of the DAVIS346's own shape, rounded to whole pixels, is the sensor resampled, as before
    assert np.allclose(davis346_camera(640, 480).K, native.scaled(640, 480).K)


def test_make_scene_rejects_bad_arguments():
    with pytest.raises(ValueError, match="name"):
        make_scene("moon_landing")
    with pytest.raises(ValueError, match="seed"):
        make_scene("slider", seed=-1)
    with pytest.raises(ValueError, match="duration_s"):
        make_scene("slider", duration_s=0.0)


# -- textures ---------------------------------------------------------------------------------
def test_textures_are_deterministic_tileable_and_in_range():
    a = make_texture("asphalt", seed=4, size=64)
    np.testing.assert_array_equal(a.values, make_texture("asphalt", seed=4, size=64).values)
    assert not np.array_equal(a.values, make_texture("asphalt", seed=5, size=64).values)
    noise = make_texture("rock", seed=1, size=128).values
    # The jump across the wrap-around seam is like any other neighbouring difference.
    interior = np.abs(np.diff(noise, axis=1)).mean()
    seam = np.abs(noise[:, 0] - noise[:, -1]).mean()
    assert seam < 2.0 * interior
    assert make_texture("foliage", seed=0, size=64).alpha is not None
    with pytest.raises(ValueError):
        make_texture("plasma")
    with pytest.raises(ValueError):
        Texture(np.zeros((10, 10)))


def test_atlas_levels_wrap_and_average():
    texture = Texture(np.tile([[0.0, 255.0], [255.0, 0.0]], (8, 8)))  # 16x16 checkerboard
    atlas = TextureAtlas.build([texture], 16)
    assert atlas.levels == 3
    x, y = atlas.origins[0, 1].astype(int)
    np.testing.assert_allclose(atlas.image[y: y + 9, x: x + 9], 127.5)  # level 1 averages the checkerboard


# -- RGB-D scene --------------------------------------------------------------------------------
def test_rgbd_scene_reproduces_reference_and_is_consistent(scenes):
    source = scenes["rotation"]
    image, depth = source.render(1.0)
    trajectory = SinusoidalTrajectory(
        R0=np.eye(3), p0=[0.0, 0.0, 0.0], velocity=[0.05, 0.0, 0.02],
        rotation_terms=np.array([[0.5, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0]]),
    )
    scene = RGBDScene(image, depth, source.camera.K, trajectory)
    again, depth0 = scene.render(0.0)
    np.testing.assert_allclose(again, image, atol=1e-3)
    np.testing.assert_allclose(depth0, depth, rtol=1e-5)
    image_a, depth_a = scene.render(0.3)
    image_b, depth_b = scene.render(0.4)
    assert np.isfinite(depth_a).mean() > 0.85
    T_a_b = relative_pose(scene.pose(0.3), scene.pose(0.4))
    warped, valid = warp_image(image_a, depth_b, T_a_b, scene.camera.K, depth_a=depth_a)
    error = np.abs(warped - image_b)[valid]
    assert valid.mean() > 0.8
    assert error.mean() < 0.3 * np.abs(image_a - image_b)[valid].mean()
    # Its ground truth agrees with the planar scene rendered from the same pose.
    T_w_c = source.pose(1.0) @ scene.pose(0.3)
    _, truth = source.render_pose(T_w_c)
    both = np.isfinite(truth) & np.isfinite(depth_a)
    assert np.median(np.abs(depth_a[both] - truth[both]) / truth[both]) < 1e-3


def test_rgbd_scene_validates_input():
    K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    trajectory = SinusoidalTrajectory(R0=np.eye(3), p0=[0, 0, 0])
    with pytest.raises(ValueError, match="depth"):
        RGBDScene(np.zeros((30, 40)), np.ones((30, 41)), K, trajectory)
    with pytest.raises(ValueError, match="depth"):
        RGBDScene(np.zeros((30, 40)), np.full((30, 40), np.nan), K, trajectory)
    with pytest.raises(TypeError, match="trajectory"):
        RGBDScene(np.zeros((30, 40)), np.ones((30, 40)), K, object())


# -- simulation and files --------------------------------------------------------------------
def test_simulate_scene_and_file_round_trip(tmp_path):
    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import load_sequence, simulate_scene

    scene = make_scene("slider", seed=0, width=64, height=48, texture_size=64)
    simulator = EventSimulator(**scene.recommended_simulator, seed=0)
    sequence = simulate_scene(scene, 0.1, simulator, lam=0.5, depth_times_s=[0.0, 0.05, 0.1],
                              t_offset_us=1_000_000, max_step_s=5e-3)
    events = sequence.events
    assert len(events) > 200 and events.sensor_size == (64, 48)
    assert events.t.min() >= 1_000_000 and events.t.max() <= 1_100_000
    steps = np.diff(sequence.frame_t_us)
    assert steps.min() >= 1 and steps.max() <= 5000
    assert sequence.depth.shape == (3, 48, 64) and sequence.depth_t_us.tolist() == [1_000_000, 1_050_000, 1_100_000]
    np.testing.assert_allclose(sequence.depth[1], scene.render(0.05)[1])
    np.testing.assert_allclose(sequence.poses[0], scene.pose(0.0))
    path = sequence.save(tmp_path / "slider.h5")
    assert [p.name for p in tmp_path.iterdir()] == ["slider.h5"]
    loaded = load_sequence(path)
    np.testing.assert_array_equal(loaded.events.t, events.t)
    np.testing.assert_array_equal(loaded.events.x, events.x)
    np.testing.assert_array_equal(loaded.depth, sequence.depth)
    np.testing.assert_array_equal(loaded.poses_t_us, sequence.poses_t_us)
    np.testing.assert_allclose(loaded.K, scene.camera.K)
    assert loaded.attrs["simulator"]["cp"] == pytest.approx(0.2)
    with pytest.raises(FileExistsError):
        sequence.save(path)
    # a second writer of the same path is locked out for the whole save (events, ground truth, rename)
    from cmax.io.atomic import OutputLockedError, PathLock, lock_path

    with PathLock(lock_path(path), path):
        with pytest.raises(OutputLockedError):
            sequence.save(path, overwrite=True)
    assert load_sequence(path).depth.shape == (3, 48, 64)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["slider.h5"]
    with pytest.raises(ValueError, match="lam"):
        simulate_scene(scene, 0.1, simulator, lam=1.5)


_KILLED_SAVE = """
import os, sys
import cmax.sim.synthetic as synthetic
from cmax.sim.esim import EventSimulator
from cmax.sim.presets import make_scene
scene = make_scene("slider", seed=0, width=64, height=48, texture_size=64)
sequence = synthetic.simulate_scene(scene, 0.05, EventSimulator(**scene.recommended_simulator, seed=0),
                                    depth_times_s=[0.0, 0.05], max_step_s=5e-3)
synthetic.write_ground_truth = lambda file, sequence: os._exit(9)   # killed before the ground truth is written
sequence.save(sys.argv[1])
"""


def test_a_save_touches_no_user_file_and_a_killed_one_leaves_nothing_that_looks_complete(tmp_path):
    """SyntheticSequence.save (cmax scene -o) used a fixed <path>.tmp (was: a user's room.h5.tmp deleted; a save
    killed before its ground truth left an events-only room.h5.tmp that passed verify_h5): now the private
    exclusive temporary of cmax.io.atomic, with gt/ written before the completion record."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from cmax.io.h5 import verify_h5
    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import load_sequence, simulate_scene

    path = tmp_path / "room.h5"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(path)], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 9, done.stderr
    left = list(tmp_path.iterdir())
    assert not path.exists() and not any(p.name.endswith(".tmp") for p in left)
    assert any(p.name.endswith(".partial") for p in left)    # the private temporary, under no user's name
    for leftover in left:   # whatever the kill left (the temporary, the lock file) is refused as incomplete
        with pytest.raises((ValueError, OSError)):
            verify_h5(leftover)
    (tmp_path / "room.h5.tmp").write_text("user data")
    scene = make_scene("slider", seed=0, width=64, height=48, texture_size=64)
    sequence = simulate_scene(scene, 0.05, EventSimulator(**scene.recommended_simulator, seed=0),
                              depth_times_s=[0.0, 0.05], max_step_s=5e-3)
    sequence.save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room.h5", "room.h5.tmp"]   # the leftover removed
    assert (tmp_path / "room.h5.tmp").read_text() == "user data"
    assert verify_h5(path) == len(sequence.events) and load_sequence(path).depth.shape == (2, 48, 64)


def test_a_loaded_sequence_gives_the_motion_and_depth_of_a_window(tmp_path):
    """pose_at / motion / depth_at of a saved and loaded sequence against the scene itself (analytic poses,
    rendered depth): exact at the stored times, geodesic interpolation in between."""
    from cmax.geometry import invert_pose
    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import load_sequence, simulate_scene

    scene = make_scene("indoor_flying", seed=3, width=48, height=36, texture_size=64)
    sequence = simulate_scene(scene, 0.2, EventSimulator(**scene.recommended_simulator, seed=0),
                              depth_times_s=[0.0, 0.1, 0.2], t_offset_us=2_000_000, max_step_s=5e-3)
    loaded = load_sequence(sequence.save(tmp_path / "room.h5"))
    k = len(loaded.poses_t_us) // 2
    np.testing.assert_allclose(loaded.pose_at(int(loaded.poses_t_us[k])), scene.pose(
        (int(loaded.poses_t_us[k]) - 2_000_000) * 1e-6), atol=1e-12)
    t0, t1 = 2_031_234, 2_187_655                                   # between stored poses
    expected = invert_pose(scene.pose(0.031234)) @ scene.pose(0.187655)
    T01 = loaded.motion(t0, t1)
    assert np.abs(T01 - expected).max() < 1e-5 and np.abs(expected - np.eye(4)).max() > 1e-2
    np.testing.assert_array_equal(loaded.depth_at(2_100_000), scene.render(0.1)[1].astype(np.float32))
    np.testing.assert_array_equal(loaded.depth_at(2_104_000, max_offset_us=5_000), loaded.depth[1])
    with pytest.raises(ValueError, match=r"no depth map within 0 µs of 2104000 µs: the nearest is at 2100000 µs"):
        loaded.depth_at(2_104_000)
    with pytest.raises(ValueError, match="query_times_us must lie in"):
        loaded.motion(1_999_000, 2_100_000)
    with pytest.raises(ValueError, match="whole microseconds"):
        loaded.pose_at(2_000_000.5)


def test_time_scaled_scene_plays_the_same_path_faster():
    from cmax.sim.scenes import TimeScaledScene

    base = make_scene("indoor_flying", seed=2, width=32, height=24, duration_s=2.0, texture_size=64)
    fast = TimeScaledScene(base, 2.5)
    assert np.array_equal(fast.pose(0.4), base.pose(1.0))
    assert np.allclose(fast.twist(0.4), 2.5 * base.twist(1.0))
    intensity, depth = fast.render(0.4)
    expected = base.render(1.0)
    assert np.array_equal(intensity, expected[0]) and np.array_equal(depth, expected[1], equal_nan=True)
    # the twist is the derivative of the pose: a finite difference of the fast path agrees
    h = 1e-4
    T = invert_pose(fast.pose(0.4)) @ fast.pose(0.4 + h)
    assert np.allclose(vee(T[:3, :3] - T[:3, :3].T) / 2 / h, fast.twist(0.4)[3:], atol=1e-2)
    assert np.allclose(T[:3, 3] / h, fast.twist(0.4)[:3], atol=1e-2)
    assert fast.info.speed_range_mps == tuple(2.5 * v for v in base.info.speed_range_mps)
    for bad in (0, -1.0, float("nan"), True):
        with pytest.raises(ValueError):
            TimeScaledScene(base, bad)


# -- cmax scene --duration -----------------------------------------------------------------------
@pytest.mark.parametrize("duration", ["1e-7", "5e-7", "0"])
def test_scene_duration_shorter_than_a_microsecond_is_refused(tmp_path, capsys, duration):
    """A duration that rounds to no time step (one rendered frame, 0 events) is refused while parsing."""
    from cmax.cli import main
    from conftest import one_line_error

    status, err = one_line_error(lambda: main(["scene", "slider", "-o", str(tmp_path / "s.h5"), "--duration",
                                               duration, "--size", "32x24"]), capsys)
    assert status == 2 and "argument --duration: expected" in err, err
    assert not (tmp_path / "s.h5").exists()


def test_scene_duration_of_one_microsecond_renders_one_interval():
    from cmax.cli.scene import MIN_DURATION_S, scene_duration
    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import simulate_scene

    assert scene_duration("1e-6") == MIN_DURATION_S == 1e-6
    scene = make_scene("slider", seed=0, width=32, height=24, texture_size=64)
    sequence = simulate_scene(scene, MIN_DURATION_S, EventSimulator())
    assert list(sequence.frame_t_us) == [0, 1]           # two frames: one interval
    assert len(simulate_scene(scene, 4e-7, EventSimulator()).frame_t_us) == 1   # what the bound refuses


@pytest.mark.parametrize("duration_s", [0.2037, 0.001])
def test_ground_truth_covers_the_last_events(duration_s):
    """The pose grid (every 5 ms) and the depth grid stopped at the last multiple of their step: the last 3.7 ms of
    events had no pose (``pose_at(t_end)`` raised; EMVS cut them), a 1 ms scene had a single pose."""
    from cmax.sim import EventSimulator, make_scene, simulate_scene

    scene = make_scene("slider", seed=0, width=64, height=48, duration_s=1.0)
    seq = simulate_scene(scene, duration_s, EventSimulator(**scene.recommended_simulator, seed=0))
    end_us = int(round(duration_s * 1e6))
    assert seq.poses_t_us[-1] == end_us >= seq.events.t_end and seq.depth_t_us[-1] == end_us
    assert len(seq.poses_t_us) >= 2
    np.testing.assert_allclose(seq.pose_at(seq.events.t_end), scene.pose(seq.events.t_end * 1e-6), atol=1e-9)


def test_a_scene_whose_events_outgrow_memory_stops_when_they_do(monkeypatch, tmp_path, capsys):
    """`cmax scene indoor_flying --duration 600` makes about 1.3 M events/s, all held until saved: was 7.8e8
    events (about 20 GB with the final concatenation) after hours of work, past cmax.events.MAX_EVENTS."""
    import cmax.events
    from cmax.cli import main
    from cmax.events import EventLimitError
    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("rotation", seed=0, width=64, height=48, duration_s=1.0)
    whole = simulate_scene(scene, 0.2, EventSimulator(**scene.recommended_simulator))
    monkeypatch.setattr(cmax.events, "MAX_EVENTS", len(whole.events) // 4)
    with pytest.raises(EventLimitError, match=r"the scene made [\d,]+ events in its first 0\.0\d+ s of 0\.2 s, "
                       r"more than cmax.events.MAX_EVENTS=[\d,]+ .*simulate about 0\.0\d+ s or less"):
        simulate_scene(scene, 0.2, EventSimulator(**scene.recommended_simulator))
    output = tmp_path / "room.h5"
    assert main(["scene", "rotation", "-o", str(output), "--duration", "0.2", "--size", "64x48"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("cmax scene: error: the scene made ") and "MAX_EVENTS" in err
    assert not output.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("width, height", [(1, 48), (64, 1), (1, 1)])
def test_make_scene_refuses_an_image_one_pixel_across(width, height):
    """Was: accepted; simulating it then failed inside torch (`self.stride(-1) must be 1 to view Long as Int`)
    or numpy (`Shape of array too small to calculate a numerical gradient`)."""
    with pytest.raises(ValueError, match=rf"width and height must be at least 2 pixels .* got {width}x{height}"):
        make_scene("slider", width=width, height=height, texture_size=64)


def test_the_smallest_scene_make_scene_accepts_simulates():
    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("slider", width=2, height=2, duration_s=0.05, texture_size=64)
    sequence = simulate_scene(scene, 0.02, EventSimulator(**scene.recommended_simulator))
    assert (sequence.events.width, sequence.events.height) == (2, 2)
