"""EMVS: geometry of the transfer, voting paths, depth of a known plane, pose inputs, bad input, CLI."""
from __future__ import annotations

import json
import types

import cv2
import h5py
import numpy as np
import pytest

from cmax import Camera, Events
from cmax.emvs import EMVS, DSI, SemiDenseDepth, as_trajectory, read_tum_trajectory, semi_dense_depth
from cmax.emvs.dsi import (base_plane_homographies, bilinear_splat, plane_depths, plane_transfer, project_packets,
                           splat_votes)
from cmax.emvs.gather import gather_votes
from cmax.geometry import se3_exp
from cmax.sim.esim import EventSimulator

PLANE_DEPTH = 2.0


def _plane_sequence(width=120, height=90, focal=150.0, depth=PLANE_DEPTH, travel=0.6, frames=241, seed=0):
    """Events of a fronto-parallel textured plane at ``depth`` seen by a camera sliding along x.

    A point X on the plane projects to ``u = f (X - tx) / Z + cx``, so the frame at camera
    position ``tx`` is the texture shifted by ``f tx / Z`` pixels (exact, by construction).
    """
    rng = np.random.default_rng(seed)
    margin = int(np.ceil(focal * travel / depth)) + 8
    noise = rng.random((height + 2 * margin, width + 2 * margin)).astype(np.float32)
    texture = cv2.GaussianBlur(noise, (0, 0), 2.0)
    texture = 30 + 200 * (texture - texture.min()) / (texture.max() - texture.min())
    times_us = np.linspace(0, 300_000, frames).round().astype(np.int64)
    tx = np.linspace(-travel / 2, travel / 2, frames)
    images = [cv2.warpAffine(texture, np.array([[1.0, 0, focal * x / depth + margin], [0, 1.0, margin]]),
                             (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP) for x in tx]
    events = EventSimulator(cp=0.15, cn=0.15).simulate(np.stack(images), times_us)
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, 0, 3] = tx
    camera = Camera.from_intrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)
    return events, camera, (times_us, poses)


@pytest.fixture(scope="module")
def plane():
    return _plane_sequence()


@pytest.fixture(scope="module")
def plane_result(plane):
    events, camera, poses = plane
    return EMVS(camera, depth_range=(1.0, 4.0), n_planes=100).run(events, poses)


# -- geometry --------------------------------------------------------------------------------
def test_plane_depths_uniform_in_inverse_depth():
    depths = plane_depths((0.5, 5.0), 10)
    assert depths[0] == pytest.approx(0.5) and depths[-1] == pytest.approx(5.0)
    np.testing.assert_allclose(np.diff(1.0 / depths), (1 / 5.0 - 1 / 0.5) / 9)


def _intersect(K, R, C, pixel, z):
    """Reference pixel where the ray of ``pixel`` from camera (R, C) meets Z_ref = z (direct 3D solve)."""
    d = R @ np.linalg.solve(K, [pixel[0], pixel[1], 1.0])
    point = C + (z - C[2]) / d[2] * d
    p = K @ (point / point[2])
    return p[:2]


def test_base_positions_and_affine_transfer_match_ray_plane_intersections():
    rng = np.random.default_rng(3)
    K = np.array([[200.0, 0.5, 118.0], [0.0, 190.0, 92.0], [0.0, 0.0, 1.0]])
    depths = plane_depths((0.8, 6.0), 12)
    for _ in range(5):
        T = se3_exp(np.r_[rng.normal(0, 0.15, 3), rng.normal(0, 0.1, 3)])
        R, C = T[:3, :3], T[:3, 3]
        transfer = plane_transfer(C, depths, K)
        pixels = rng.uniform([0, 0], [240, 180], (20, 2))
        H = base_plane_homographies(np.stack([T, T]), depths[transfer.base], K)
        base, hits = project_packets(pixels, H, np.array([12, 8]))
        assert hits.all()
        for pixel, x_b in zip(pixels, base):
            np.testing.assert_allclose(x_b, _intersect(K, R, C, pixel, depths[transfer.base]), atol=1e-8)
            for i in np.flatnonzero(transfer.valid):
                expected = _intersect(K, R, C, pixel, depths[i])
                np.testing.assert_allclose(transfer.scales[i] * x_b + transfer.offsets[i], expected, atol=1e-7)


def test_transfer_skips_planes_behind_the_camera():
    K = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    depths = plane_depths((1.0, 4.0), 8)
    transfer = plane_transfer(np.array([0.0, 0.0, 1.5]), depths, K)
    np.testing.assert_array_equal(transfer.valid, depths > 1.5)
    assert transfer.valid[transfer.base] and np.all(transfer.scales[transfer.valid] > 0)
    assert plane_transfer(np.array([0.0, 0.0, 5.0]), depths, K) is None


def test_bilinear_splat_matches_per_point_weights():
    x = np.array([[1.25, 3.0, 0.5, 4.9]])
    y = np.array([[2.5, 0.0, 3.75, 1.0]])
    out = bilinear_splat(x, y, np.array([1.0, 2.0, 1.0, 1.0]), 5, 4)[0]
    expected = np.zeros((4, 5))
    for xi, yi, w in zip(x[0], y[0], [1.0, 2.0, 1.0, 1.0]):
        for X in range(5):
            for Y in range(4):
                expected[Y, X] += w * max(0, 1 - abs(xi - X)) * max(0, 1 - abs(yi - Y))
    np.testing.assert_allclose(out, expected, atol=1e-12)
    assert out.sum() == pytest.approx(1.0 + 2.0 + 0.25 + 0.1)  # y = 3.75 keeps 0.25, x = 4.9 keeps 0.1


# -- the two voting paths ----------------------------------------------------------------------
def _random_case(centre, n=3000, seed=0):
    K = np.array([[100.0, 0, 60], [0, 100, 45], [0, 0, 1]])
    depths = plane_depths((1.0, 4.0), 20)
    rng = np.random.default_rng(seed)
    positions = np.column_stack([rng.uniform(10, 110, n), rng.uniform(10, 80, n)])
    return positions, plane_transfer(np.asarray(centre, float), depths, K)


@pytest.mark.parametrize("subpixel", [4, 32])
def test_gather_equals_splat_to_the_rounding_bound_for_translations(subpixel):
    positions, transfer = _random_case([0.2, 0.05, 0.0])
    fast = np.zeros((20, 90, 120), np.float32)
    exact = np.zeros_like(fast)
    gather_votes(fast, positions, transfer, subpixel=subpixel)
    splat_votes(exact, positions, transfer)
    # Offsets rounded to 1/S px: every vote moves by <= 1/(2S) px per axis, so the L1
    # change of one event's bilinear weights is <= 2 (|dx| + |dy|) <= 2 / S.
    l1 = np.abs(fast - exact).sum(axis=(1, 2))
    assert np.all(l1 <= 2 * len(positions) / subpixel)
    np.testing.assert_allclose(fast.sum(axis=(1, 2)), exact.sum(axis=(1, 2)), rtol=1e-5)


def test_gather_with_scaled_planes_keeps_votes_and_matches_smoothed_splat():
    positions, transfer = _random_case([0.05, 0.02, 0.3])  # moving along the optical axis: a_i != 1
    assert np.ptp(transfer.scales[transfer.valid]) > 0.2
    fast = np.zeros((20, 90, 120), np.float32)
    exact = np.zeros_like(fast)
    gather_votes(fast, positions, transfer)
    splat_votes(exact, positions, transfer)
    # Each event keeps one vote per plane (the 1/a^2 of the resampling), up to border effects.
    np.testing.assert_allclose(fast.sum(axis=(1, 2)), exact.sum(axis=(1, 2)), rtol=0.01)
    # The bilinear gather adds one bilinear blur: both agree once smoothed.
    blur = lambda v: np.stack([cv2.GaussianBlur(p, (0, 0), 1.5) for p in v])  # noqa: E731
    assert np.abs(blur(fast) - blur(exact)).max() <= 0.08 * blur(exact).max()


# -- depth of a known plane --------------------------------------------------------------------
def test_plane_depth_recovered_within_two_percent(plane, plane_result):
    result = plane_result
    assert isinstance(result, SemiDenseDepth)
    assert result.depth.shape == (90, 120) and result.depth.dtype == np.float32
    assert 0.05 < result.mask.mean() < 0.6  # semi-dense: neither empty nor everything
    assert np.isnan(result.depth[~result.mask]).all() and np.isfinite(result.depth[result.mask]).all()
    assert abs(np.median(result.depth[result.mask]) / PLANE_DEPTH - 1) < 0.02
    assert np.mean(np.abs(result.depth[result.mask] / PLANE_DEPTH - 1) < 0.05) > 0.75
    events = plane[0]
    assert result.t_ref_us == (int(events.t[0]) + int(events.t[-1])) // 2
    assert result.n_planes == 100 and result.depth_range == pytest.approx((1.0, 4.0))


def test_exact_splat_voting_recovers_the_plane_too(plane):
    events, camera, poses = plane
    result = EMVS(camera, depth_range=(1.0, 4.0), n_planes=40, voting="splat").run(events, poses)
    assert abs(np.median(result.depth[result.mask]) / PLANE_DEPTH - 1) < 0.02


def test_reference_pose_and_points_in_the_world_frame(plane, plane_result):
    result = plane_result
    times, poses = plane[2]
    x_ref = np.interp(result.t_ref_us, times, poses[:, 0, 3])
    np.testing.assert_allclose(result.T_w_ref[:3, 3], [x_ref, 0, 0], atol=1e-9)
    assert result.points.shape == (int(result.mask.sum()), 3)
    # Back in the reference camera, every point projects onto its pixel with its depth.
    points_ref = result.points - result.T_w_ref[:3, 3]
    rows, cols = np.nonzero(result.mask)
    pixels = points_ref @ result.K.T
    np.testing.assert_allclose(pixels[:, 0] / pixels[:, 2], cols, atol=1e-6)
    np.testing.assert_allclose(pixels[:, 1] / pixels[:, 2], rows, atol=1e-6)
    np.testing.assert_allclose(points_ref[:, 2], result.depth[rows, cols], rtol=1e-6)


def test_depth_from_a_synthetic_dsi():
    votes = np.zeros((5, 20, 30), np.float32)
    depths = plane_depths((1.0, 5.0), 5)
    votes[3, 5:15, 10] = 10.0  # a vertical line at plane 3
    votes[1, 8, 20] = 6.0      # one point at plane 1
    votes += 0.1
    dsi = DSI(votes, depths, np.array([[50.0, 0, 15], [0, 50, 10], [0, 0, 1]]), 0, np.eye(4), 1, 0.0)
    result = semi_dense_depth(dsi, median_size=1)
    assert result.mask[5:15, 10].all() and result.mask[8, 20]
    assert result.mask.sum() == 11
    np.testing.assert_allclose(result.depth[5:15, 10], depths[3], rtol=1e-6)
    assert result.depth[8, 20] == pytest.approx(depths[1])
    np.testing.assert_allclose(result.confidence[5:15, 10], 10.1, rtol=1e-6)


def test_plot_and_ply(plane_result, tmp_path):
    png = plane_result.plot(tmp_path / "depth.png")
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] >= 90 and image.shape[1] > 2 * 120
    ply = plane_result.save_ply(tmp_path / "points.ply")
    data = ply.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert f"element vertex {len(plane_result.points)}".encode() in header
    np.testing.assert_allclose(np.frombuffer(body, "<f4").reshape(-1, 3), plane_result.points, rtol=1e-6)
    text = plane_result.save_ply(tmp_path / "points_ascii.ply", binary=False).read_text()
    values = np.loadtxt(text.split("end_header\n", 1)[1].splitlines())
    np.testing.assert_allclose(values, plane_result.points, atol=1e-6)
    assert not list(tmp_path.glob("*.partial"))


def test_confidence_panel_title_says_which_grey_is_which():
    """Was: "confidence 0-291 votes" over a grey map: white or black for many votes left to guess."""
    from cmax.emvs.result import confidence_title

    assert confidence_title(291.0) == "votes: black >= 291"


def test_ply_header_names_the_frame_its_points_are_in(plane_result, tmp_path):
    """Was: points.ply said only "written by cmax.emvs": camera or world frame, metres or not, left to guess.
    The header names the world frame of the poses, and the points are that: T_w_ref of each masked pixel's
    back-projected depth."""
    header = plane_result.save_ply(tmp_path / "p.ply").read_bytes().split(b"end_header\n", 1)[0].decode()
    assert "comment x y z: world frame of the poses (T_w_ref of depth.npz" in header
    rows, cols = np.nonzero(plane_result.mask)
    rays = np.linalg.solve(plane_result.K, np.stack([cols, rows, np.ones_like(cols)]).astype(float))
    camera = rays * plane_result.depth[rows, cols]
    world = (plane_result.T_w_ref[:3, :3] @ camera + plane_result.T_w_ref[:3, 3:]).T
    np.testing.assert_allclose(np.sort(world, axis=0), np.sort(plane_result.points, axis=0), atol=1e-4)


def test_picture_takes_its_colour_scale_from_the_map_not_from_the_planes_range():
    """A DSI over 0.5-200 m (a hike's range) with its depths within 1.8-2.7 m: drawn on the DSI's range, all
    of it fell in the darkest fifth of the colours; the picture takes the map's own percentiles."""
    from cmax import viz

    depths = plane_depths((0.5, 200.0), 60)
    votes = np.full((60, 20, 30), 0.1, np.float32)
    near, far = np.argmin(np.abs(depths - 1.8)), np.argmin(np.abs(depths - 2.7))
    for column, plane in enumerate(np.linspace(near, far, 30).round().astype(int)):
        votes[plane, 5:15, column] = 10.0
    result = semi_dense_depth(DSI(votes, depths, np.array([[50.0, 0, 15], [0, 50, 10], [0, 0, 1]]), 0, np.eye(4), 1,
                                  0.0), median_size=1)
    own = viz.DepthScale.from_depths(result.depth[result.mask])
    assert 1.7 < own.near < own.far < 2.8
    panel = viz.depth_panel(np.where(result.mask, result.depth, np.nan), own,
                            f"semi-dense depth, {int(result.mask.sum())} px")
    np.testing.assert_array_equal(result.image(zoom=1)[:panel.shape[0], -panel.shape[1]:], panel)   # padded below
    assert not np.array_equal(result.image(), result.image((0.5, 200.0)))


def test_the_share_of_the_depth_map_on_the_first_and_last_planes():
    """30 columns: 3 on the nearest plane, 6 on the farthest, the rest between: the shares are those columns' share
    of the mask."""
    depths = plane_depths((0.5, 200.0), 60)
    votes = np.full((60, 20, 30), 0.1, np.float32)
    between = list(np.linspace(5, 50, 21).round().astype(int))
    planes = between[:10] + [0] * 3 + [59] * 6 + between[10:]                 # columns 10-12 near, 13-18 far
    for column, plane in enumerate(planes):
        votes[plane, 5:15, column] = 10.0
    result = semi_dense_depth(DSI(votes, depths, np.array([[50.0, 0, 15], [0, 50, 10], [0, 0, 1]]), 0, np.eye(4), 1,
                                  0.0), median_size=1)
    mask = result.mask
    near, far = mask[:, 10:13], mask[:, 13:19]
    np.testing.assert_allclose(result.depth[:, 10:13][near], depths[0], rtol=1e-5)
    np.testing.assert_allclose(result.depth[:, 13:19][far], depths[-1], rtol=1e-5)
    assert near.sum() >= 10 and far.sum() >= 20                   # the adaptive mask keeps the band's edges
    shares = result.on_bounds()
    assert shares["near"] == pytest.approx(near.sum() / mask.sum()) and shares["far"] == pytest.approx(far.sum() / mask.sum())


# -- pose inputs -------------------------------------------------------------------------------
def test_pose_input_forms_give_the_same_depth(plane, plane_result):
    events, camera, (times, poses) = plane
    emvs = EMVS(camera, depth_range=(1.0, 4.0), n_planes=100)
    from cmax.fitting.sequence import SequenceResult

    for form in ([times, poses], SequenceResult((), times, poses), types.SimpleNamespace(times_us=times, poses=poses)):
        result = emvs.run(events, form)
        np.testing.assert_array_equal(result.mask, plane_result.mask)
        np.testing.assert_array_equal(result.depth, plane_result.depth)


def test_tum_trajectory_round_trip(tmp_path):
    from cmax.cli.fit import tum_lines

    rng = np.random.default_rng(0)
    times = np.array([1_700_000_000_123_456, 1_700_000_000_223_457, 1_700_000_000_323_458])
    poses = se3_exp(rng.normal(0, 0.3, (3, 6)))
    path = tmp_path / "trajectory.txt"
    path.write_text("# t tx ty tz qx qy qz qw\n" + "\n".join(tum_lines(times, poses)) + "\n\n")
    read_times, read_poses = read_tum_trajectory(path)
    np.testing.assert_array_equal(read_times, times)  # seconds parsed as decimals: no lost microseconds
    np.testing.assert_allclose(read_poses, poses, atol=1e-8)


def test_ecd_groundtruth_reads(shared_data):
    times, poses = read_tum_trajectory(shared_data / "ecd_slider_depth" / "groundtruth.txt")
    assert len(times) == 339 and times[0] == 22292  # 0.022291582 s, rounded to µs
    assert poses[0, 0, 3] == pytest.approx(0.1116875) and poses[-1, 0, 3] == pytest.approx(1.092, abs=1e-3)


# -- bad input ---------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, match", [
    ({"depth_range": (2.0, 1.0)}, "depth_range"), ({"depth_range": (0.0, 1.0)}, "depth_range"),
    ({"depth_range": (-1.0, 1.0)}, "depth_range"), ({"depth_range": (1.0, 1.0)}, "depth_range"),
    ({"depth_range": (1.0, np.inf)}, "depth_range"), ({"depth_range": "far"}, "depth_range"),
    ({"n_planes": 1}, "n_planes"), ({"n_planes": 2.5}, "n_planes"), ({"voting": "nearest"}, "voting"),
    ({"events_per_pose": 0}, "events_per_pose"), ({"median_size": 4}, "median_size"),
    ({"threshold_kernel": 1}, "threshold_kernel"), ({"subpixel": 0}, "subpixel"),
])
def test_bad_settings_raise(kwargs, match):
    camera = Camera.from_intrinsics(100, 100, 60, 45, 120, 90)
    with pytest.raises(ValueError, match=match):
        EMVS(camera, **kwargs)


def test_a_dsi_larger_than_memory_is_refused_before_any_work():
    """100000 planes of a 240x180 sensor asked numpy for 16 GiB (a lazily touched calloc: the OOM killer, not an
    error, on a machine with less)."""
    camera = Camera.from_intrinsics(100, 100, 120, 90, 240, 180)
    with pytest.raises(ValueError, match=r"n_planes=100000 planes of 240x180 make a Disparity Space Image of 16\.1 GiB"
                                         r", more than cmax\.emvs\.core\.MAX_DSI_BYTES \(4 GiB\): give at most "
                                         r"24,855 planes"):
        EMVS(camera, n_planes=100_000)
    EMVS(camera, n_planes=24_855)      # 3.99999 GiB: allowed (nothing is allocated before run)


def test_camera_must_be_a_camera():
    with pytest.raises(TypeError, match="camera"):
        EMVS(np.eye(3))


def test_bad_events_and_poses_raise(plane):
    events, camera, (times, poses) = plane
    emvs = EMVS(camera, depth_range=(1.0, 4.0))
    with pytest.raises(ValueError, match="empty"):
        emvs.run(events[:0], (times, poses))
    with pytest.raises(TypeError, match="events"):
        emvs.run(np.zeros((10, 4)), (times, poses))
    other = Events(events.x[:10], events.y[:10], events.t[:10], events.p[:10], 240, 180)
    with pytest.raises(ValueError, match="sensor"):
        emvs.run(other, (times, poses))
    with pytest.raises(ValueError, match="cover"):
        emvs.run(events, (times[10:], poses[10:]))
    with pytest.raises(ValueError, match="shape"):
        emvs.run(events, (times, poses[:, :3]))
    with pytest.raises(ValueError, match="increasing"):
        emvs.run(events, (times[::-1], poses))
    with pytest.raises(ValueError, match="rotation"):
        emvs.run(events, (times, poses * 2.0 + np.diag([0, 0, 0, -1.0])))
    with pytest.raises(TypeError, match="times_us"):
        emvs.run(events, {"times": times})
    with pytest.raises(ValueError, match="pair"):
        emvs.run(events, (times, poses, poses))


def test_bad_tum_files_raise(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("0.0 1 2 3 0 0 0\n")
    with pytest.raises(ValueError, match="8 numbers"):
        read_tum_trajectory(path)
    path.write_text("0.0 1 2 3 0 0 0 2\n")
    with pytest.raises(ValueError, match="norm"):
        read_tum_trajectory(path)
    path.write_text("0.1 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="increasing"):
        read_tum_trajectory(path)
    with pytest.raises(FileNotFoundError):
        read_tum_trajectory(tmp_path / "missing.txt")


def test_a_header_stating_another_layout_is_refused(tmp_path):
    """A header naming the quaternion w first, or times in ns, is refused; a TUM header is read as before."""
    poses = np.stack([np.eye(4)] * 2)
    poses[1, 0, 3] = 0.1
    rows = "0.0 0 0 0 0 0 0 1\n0.1 0.1 0 0 0 0 0 1\n"
    path = tmp_path / "traj.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + rows)
    times, read = read_tum_trajectory(path)
    np.testing.assert_array_equal(times, [0, 100_000])
    np.testing.assert_allclose(read, poses)
    # the same numbers, but the header says qw comes first: reading them as qx qy qz qw would turn the camera
    # 180 degrees about z (q = (0, 0, 1, 0) as xyzw) instead of the identity
    path.write_text("# timestamp tx ty tz qw qx qy qz\n" + "0.0 0 0 0 1 0 0 0\n0.1 0.1 0 0 1 0 0 0\n")
    with pytest.raises(ValueError, match=r"traj.txt: its header .* puts the quaternion's w first"):
        read_tum_trajectory(path)
    euroc = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
    path.write_text(euroc + "1403715273262142976,0,0,0,1,0,0,0\n1403715273267142912,0.1,0,0,1,0,0,0\n")
    with pytest.raises(ValueError, match=r"gives times in ns .* and puts the quaternion's w first"):
        read_tum_trajectory(path)
    path.write_text("# poses every 5 [ms] from the motion capture\n# t[s] tx ty tz qx qy qz qw\n" + rows)
    assert read_tum_trajectory(path)[0].tolist() == [0, 100_000]   # a unit in a remark is not the time column's


def test_a_headerless_first_pose_that_is_the_identity_written_wxyz_is_named(tmp_path, recwarn):
    """A trajectory starting at the identity, written qw qx qy qz without a header, read as (1, 0, 0, 0) in x y z w:
    a half turn about x, without a word (on a 6-DoF scene: median abs_rel 0.43 instead of 0.13)."""
    path = tmp_path / "wxyz.txt"
    path.write_text("0.0 0 0 0 1 0 0 0\n0.1 0.1 0 0 0.99875 0.04998 0 0\n")
    with pytest.warns(UserWarning, match=r"wxyz.txt: the first pose's quaternion \(qx qy qz qw\) is \(1, 0, 0, 0\), a "
                                         r"half turn about x, read as given; it is the identity if the columns are qw"):
        _, poses = read_tum_trajectory(path)
    np.testing.assert_allclose(poses[0, :3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)   # read as documented
    path.write_text("0.0 0 0 0 0 0 0 1\n0.1 0.1 0 0 0.04998 0 0 0.99875\n")
    recwarn.clear()
    read_tum_trajectory(path)
    assert not [w for w in recwarn if "quaternion" in str(w.message)]


def test_a_time_out_of_range_is_one_error_naming_the_line(tmp_path):
    """Nanoseconds since 1970 read as seconds overflow int64 µs (was: OverflowError from NumPy)."""
    path = tmp_path / "ns.txt"
    path.write_text("1403715273262142976 0 0 0 0 0 0 1\n1403715273267142912 0.1 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"ns.txt:1: the time 1403715273262142976 is too large for seconds .* look "
                                         r"like nanoseconds \(1403715273\.262143 s since 1970 if so\)"):
        read_tum_trajectory(path)
    path.write_text("0 0 0 0 0 0 0 1\ninf 0.1 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"ns.txt:2: the time 'inf' is not a finite number"):
        read_tum_trajectory(path)


def test_as_trajectory_reads_a_synthetic_sequence_s_ground_truth():
    from cmax.sim.synthetic import SyntheticSequence

    times = np.array([0, 5_000, 10_000])
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 0.1, 0.2]
    sequence = SyntheticSequence(Events.empty(8, 6), np.zeros((0, 6, 8), np.float32), np.zeros(0, np.int64), poses,
                                 times, np.zeros((3, 6)), np.eye(3), np.zeros(0, np.int64), {})
    got_times, got_poses = as_trajectory(sequence)
    np.testing.assert_array_equal(got_times, times)
    np.testing.assert_array_equal(got_poses, poses)
    with pytest.raises(TypeError, match=r"attributes times_us \(or poses_t_us\) and poses"):
        as_trajectory(np.eye(4))


def test_as_trajectory_rejects_fractional_microseconds():
    with pytest.raises(ValueError, match="whole microseconds"):
        as_trajectory((np.array([0.5, 1.0]), np.stack([np.eye(4)] * 2)))


# -- command line -------------------------------------------------------------------------------
def test_cli_round_trip(plane, tmp_path, capsys):
    from cmax.cli import main
    from cmax.cli.fit import tum_lines
    from cmax.io import write_h5

    events, camera, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events, source="test_emvs")
    with h5py.File(path, "a") as file:
        file["gt/K"] = camera.K
    (tmp_path / "traj.txt").write_text("\n".join(tum_lines(times, poses)) + "\n")
    out = tmp_path / "out"
    code = main(["emvs", str(path), "--poses", str(tmp_path / "traj.txt"), "-o", str(out),
                 "--depth-range", "1,4", "--planes", "100"])
    assert code == 0
    summary = capsys.readouterr().out.strip()
    assert summary.count("\n") == 0 and "median depth" in summary
    saved = np.load(out / "depth.npz")
    assert abs(np.nanmedian(saved["depth"]) / PLANE_DEPTH - 1) < 0.02
    np.testing.assert_array_equal(np.isfinite(saved["depth"]), saved["mask"])
    assert int(saved["t_ref_us"]) == (int(events.t[0]) + int(events.t[-1])) // 2
    assert cv2.imread(str(out / "depth.png")) is not None
    assert (out / "points.ply").read_bytes().startswith(b"ply\n")
    # --K overrides, --t0/--t1 cut the events (seconds after the first event); the folder holds this run's
    # results: refused without --overwrite (nothing changed), replaced with it.
    again = ["emvs", str(path), "--poses", str(tmp_path / "traj.txt"), "-o", str(out), "--depth-range",
             "1,4", "--K", f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}", "--t0", "0.05", "--t1", "0.25"]
    first = (out / "depth.npz").read_bytes()
    assert main(again) == 2 and "--overwrite replaces them" in capsys.readouterr().err
    assert (out / "depth.npz").read_bytes() == first
    code = main([*again, "--overwrite"])
    assert code == 0 and "median depth" in capsys.readouterr().out
    # poses that end before the events (cmax fit's trajectory.txt stops at its last whole window): the overlap,
    # with a note saying what was cut
    short = times < int(events.t[0]) + (int(events.t[-1]) - int(events.t[0])) * 3 // 5
    (tmp_path / "short.txt").write_text("\n".join(tum_lines(times[short], poses[short])) + "\n")
    assert main(["emvs", str(path), "--poses", str(tmp_path / "short.txt"), "-o", str(out), "--depth-range",
                 "1,4", "--overwrite"]) == 0
    captured = capsys.readouterr()
    last = int(times[short][-1])
    cut = int(np.sum(events.t > last))
    assert (f"note: the poses of {tmp_path / 'short.txt'} cover " in captured.err and f"{cut:,} events): EMVS on the "
            "overlap" in captured.err), captured.err
    saved = np.load(out / "depth.npz")
    assert int(saved["t_ref_us"]) == (int(events.t[0]) + int(events.t[events.t <= last][-1])) // 2
    assert abs(np.nanmedian(saved["depth"]) / PLANE_DEPTH - 1) < 0.02


def test_emvs_default_depth_range_is_said_and_is_the_range_it_used(plane, tmp_path, capsys):
    """Without --depth-range on a file that records no scene range (any real recording), the planes span EMVS's
    default 0.5-5 (was: without a word, while cmax fit, whose trajectory it is run on, searched its own 0.5-60):
    a note names the range, which is the one summary.json records."""
    from cmax.cli import main
    from cmax.cli.fit import tum_lines
    from cmax.io import write_h5

    events, camera, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events, source="test_emvs")
    (tmp_path / "traj.txt").write_text("\n".join(tum_lines(times, poses)) + "\n")
    assert main(["emvs", str(path), "--poses", str(tmp_path / "traj.txt"), "-o", str(tmp_path / "out"), "--K",
                 f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}", "--planes", "20"]) == 0
    err = capsys.readouterr().err
    near, far = json.loads((tmp_path / "out" / "summary.json").read_text())["depth_range"]
    assert f"note: planes over {near:g}-{far:g} m, EMVS's default depth range: --depth-range" in err, err
    assert "summary.json's depth_range" in err
    assert main(["emvs", str(path), "--poses", str(tmp_path / "traj.txt"), "-o", str(tmp_path / "given"), "--K",
                 f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}", "--planes", "20", "--depth-range", "1,4"]) == 0
    assert "planes over" not in capsys.readouterr().err   # a range given is not noted


def test_the_pile_up_on_an_end_plane_of_poses_up_to_scale_is_not_called_metres(plane, tmp_path, capsys):
    """Poses up to scale (cmax fit without --speed): the planes are not metres, nor is the pile-up on the far one
    (the plane at 2 beyond a range ending at 0.8; was: 'on the far plane (0.8 m)' beside a note saying the
    depths are not metres)."""
    from cmax.cli import main
    from cmax.cli.fit import tum_lines
    from cmax.emvs.poses import tum_header
    from cmax.io import write_h5

    events, camera, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events, source="test_emvs")
    (tmp_path / "scaled.txt").write_text("\n".join(tum_header(False) + tum_lines(times, poses)) + "\n")
    assert main(["emvs", str(path), "--poses", str(tmp_path / "scaled.txt"), "-o", str(tmp_path / "scaled"), "--K",
                 f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}", "--planes", "20", "--depth-range", "0.3,0.8"]) == 0
    err = capsys.readouterr().err
    assert "of the depth map lies on the far plane (0.8 up to scale)" in err and " m)" not in err, err


def test_cli_errors_exit_2(plane, tmp_path, capsys):
    from cmax.cli import main
    from cmax.io import write_h5

    events, _, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events)
    traj = tmp_path / "traj.txt"
    traj.write_text("0.0 0 0 0 0 0 0 1\n0.01 0 0 0 0 0 0 1\n")
    assert main(["emvs", str(path), "--poses", str(traj), "-o", str(tmp_path / "o")]) == 2
    assert "gt/K" in capsys.readouterr().err
    late = tmp_path / "late.txt"           # poses on another clock: nothing overlaps
    late.write_text("100.0 0 0 0 0 0 0 1\n100.01 0 0 0 0 0 0 1\n")
    assert main(["emvs", str(path), "--poses", str(late), "-o", str(tmp_path / "o"), "--K", "150,150,60,45"]) == 2
    err = capsys.readouterr().err
    assert "do not overlap the events" in err and "same clock" in err and err.count("\n") == 1
    assert main(["emvs", str(path), "--poses", str(tmp_path / "none.txt"), "-o", str(tmp_path / "o"),
                 "--K", "150,150,60,45"]) == 2
    with pytest.raises(SystemExit):
        main(["emvs", str(path), "--poses", str(traj), "-o", "o", "--depth-range", "1"])
    # --calib-camera where it chooses nothing (was: taken and ignored, the map made with the one K there is):
    (tmp_path / "calib.txt").write_text("150 150 60 45\n")
    capsys.readouterr()
    for camera in (["--calib", str(tmp_path / "calib.txt"), "--calib-camera", "camRect0"],
                   ["--K", "150,150,60,45", "--calib-camera", "cam1"]):
        assert main(["emvs", str(path), "--poses", str(traj), "-o", str(tmp_path / "c"), *camera]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and ("calibrates one camera (ECD calib.txt)" in err
                                         or "--calib-camera cam1 chooses a camera of a --calib file" in err), err
    assert not (tmp_path / "c").exists()


def test_a_k_of_another_sensor_size_is_refused(plane, tmp_path, capsys):
    """The calibration of 240x180 frames given for events simulated at --size 120x90: its principal point lies off
    the sensor; refused as cmax fit refuses it (was: a depth map and exit 0, without a word)."""
    from cmax.cli import main
    from cmax.cli.fit import tum_lines
    from cmax.io import write_h5

    events, camera, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events)
    (tmp_path / "traj.txt").write_text("\n".join(tum_lines(times, poses)) + "\n")
    common = ["emvs", str(path), "--poses", str(tmp_path / "traj.txt"), "--depth-range", "1,4", "--planes", "20"]
    doubled = f"{2 * camera.fx},{2 * camera.fy},{2 * camera.cx + 1},{2 * camera.cy + 1}"   # the 240x180 frames' K
    assert main([*common, "-o", str(tmp_path / "o"), "--K", doubled]) == 2
    err = capsys.readouterr().err
    assert "principal point (120, 90) lies outside the 120x90 image" in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()
    assert main([*common, "-o", str(tmp_path / "o"), "--K", f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}"]) == 0


def test_a_k_unlike_a_camera_s_for_the_sensor_is_noted(plane, tmp_path, capsys):
    """The K of frames twice this size (a --size half the video's) with its principal point just inside the
    sensor: run, with the note cmax fit warns (was: nothing)."""
    from cmax.cli import main
    from cmax.cli.fit import tum_lines
    from cmax.io import write_h5

    events, camera, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events)
    (tmp_path / "traj.txt").write_text("\n".join(tum_lines(times, poses)) + "\n")
    common = ["emvs", str(path), "--poses", str(tmp_path / "traj.txt"), "--depth-range", "1,4", "--planes", "20"]
    assert main([*common, "-o", str(tmp_path / "o"), "--K", f"{2 * camera.fx},{2 * camera.fy},119,89"]) == 0
    err = capsys.readouterr().err
    assert "note: K (fx 300, fy 300, cx 119, cy 89) is unlike a camera's for a 120x90 sensor" in err, err
    assert main([*common, "-o", str(tmp_path / "p"), "--K", f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}"]) == 0
    assert "unlike a camera's" not in capsys.readouterr().err


# -- real frames (slow) ---------------------------------------------------------------------------
@pytest.mark.slow
def test_ecd_slider_depth_structures(shared_data, tmp_path):
    from benchmarks.ecd_slider_emvs import run_slider

    report = run_slider(shared_data / "ecd_slider_depth", tmp_path / "ecd_slider_emvs.png", method="linear")
    assert (tmp_path / "ecd_slider_emvs.png").is_file()
    assert report.mask_fraction > 0.02
    depths = report.depths[report.mask]
    assert 0.47 <= np.median(depths) <= 2.4
    # The scene has structures at several depths: a far wall with a dartboard at the top of the image
    # and nearer objects on the table below it.
    structures = report.structures
    assert len(structures) >= 2
    near, far = structures[0], structures[-1]
    assert near.median_depth_m < 0.7 * far.median_depth_m
    assert far.centroid_xy[1] < near.centroid_xy[1]


@pytest.mark.parametrize("planes", ["0", "1", "two"])
def test_planes_below_two_are_refused_with_one_bound(tmp_path, capsys, planes):
    """``--planes 0`` said ">= 1", then ``--planes 1`` said ">= 2": one bound, named once."""
    from cmax.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["emvs", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "o"), "--planes", planes])
    assert exit_.value.code == 2
    assert f"argument --planes: expected a whole number >= 2, got '{planes}'" in capsys.readouterr().err


def test_a_trajectory_in_microseconds_read_as_seconds_is_refused(plane, tmp_path, capsys):
    """TUM times in µs (0, 5000, ...) put every event between the first two poses, 10^6 times too far apart:
    was an empty map, exit 0, "no camera motion"; now one line naming the unit."""
    from cmax.cli import main
    from cmax.cli.fit import tum_lines
    from cmax.io import write_h5

    events, camera, (times, poses) = plane
    path = write_h5(tmp_path / "plane.h5", events)
    lines = tum_lines(times, poses)
    (tmp_path / "us.txt").write_text("\n".join(f"{float(line.split()[0]) * 1e6:.0f} " + line.split(" ", 1)[1]
                                               for line in lines) + "\n")
    K = f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}"
    assert main(["emvs", str(path), "--poses", str(tmp_path / "us.txt"), "--K", K, "-o", str(tmp_path / "o"),
                 "--depth-range", "1,4"]) == 2
    err = capsys.readouterr().err
    assert "lies between two poses" in err and "times in µs read as seconds" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("time, message", [
    ("1403636579763555584", r"the time 1403636579763555584 is too large for seconds \(TUM's unit\): these look like "
                            r"nanoseconds \(1403636579.763556 s since 1970 if so\)"),
    ("1403636579763555", r"the time 1403636579763555 is too large for seconds .*: these look like microseconds"),
    ("nan", "the time 'nan' is not a finite number of seconds"),
    ("inf", "the time 'inf' is not a finite number of seconds"),
])
def test_tum_times_in_nanoseconds_or_not_finite_are_refused_naming_the_line(tmp_path, time, message):
    """A TUM file of nanosecond times (a EuRoC / ROS export) failed with 'OverflowError: Python int too large to
    convert to C long' (a traceback in cmax emvs); NaN with 'cannot convert NaN to integer', naming nothing."""
    path = tmp_path / "traj.txt"
    path.write_text(f"{time} 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"traj.txt:1: " + message):
        read_tum_trajectory(path)


def test_the_votes_are_projected_a_block_at_a_time_with_the_same_dsi(plane, monkeypatch):
    """dsi() undistorted and projected every event of the span at once (float32 pixels, float64 positions: with
    the events, ~45 bytes an event, 2.7 GB for 60 M events); a block of groups at a time gives the same votes."""
    import cmax.emvs.core as core

    events, camera, poses = plane
    emvs = EMVS(camera, depth_range=(1.0, 4.0), n_planes=30)
    whole = emvs.dsi(events, poses)
    sizes = []

    def spy(pixels, homographies, packet_sizes):
        sizes.append(len(pixels))
        return project_packets(pixels, homographies, packet_sizes)

    monkeypatch.setattr(core, "project_packets", spy)
    monkeypatch.setattr(core, "PROJECT_CHUNK_EVENTS", len(events) // 10)
    blocks = emvs.dsi(events, poses)
    assert len(sizes) >= 5 and max(sizes) <= len(events) // 10 + emvs.events_per_transfer, (len(events), sizes)
    assert sum(sizes) == len(events)
    np.testing.assert_array_equal(blocks.votes, whole.votes)
    assert blocks.n_events == whole.n_events > 0


def test_cmax_emvs_shows_its_progress_in_a_terminal(slider_file, tmp_path, capsys, monkeypatch):
    """cmax emvs voted 60 M events for a minute with nothing on the screen (EMVS(progress=) was never set)."""
    import sys

    from cmax.cli import main

    capsys.readouterr()
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    for quiet, name in ((False, "bar"), (True, "quiet")):
        argv = ["emvs", str(slider_file), "-o", str(tmp_path / name), "--planes", "20"] + (["--quiet"] if quiet else [])
        assert main(argv) == 0
        err = capsys.readouterr().err
        assert ("EMVS:" in err and "group" in err) != quiet, err


def test_a_rectified_fisheye_camera_recovers_the_plane_in_its_rectified_frame(plane):
    """EMVS on a fisheye (equidistant) camera with a rectification R: the plane sequence is the rectified view
    (fronto-parallel there), its events are moved onto the fisheye sensor by the forward model and the poses are
    given as the camera's, T_w_c = T_w_rect [R | 0]; EMVS must undistort, rectify and turn the poses back."""
    events, pinhole, (times, T_w_rect) = plane
    R = cv2.Rodrigues(np.array([0.02, np.deg2rad(10.0), 0.03]))[0]
    lens = Camera(np.array([[140.0, 0, 61.0], [0, 141.0, 43.0], [0, 0, 1]]), 120, 90, [-0.05, 0.01, 0.0, 0.0],
                  "equidistant", R, pinhole.K)
    sensor = np.rint(lens.distort_points(np.column_stack([events.x, events.y]).astype(float)))
    keep = np.isfinite(sensor).all(axis=1) & (sensor >= 0).all(axis=1) & (sensor < [120, 90]).all(axis=1)
    fisheye_events = Events(sensor[keep, 0], sensor[keep, 1], events.t[keep], events.p[keep], 120, 90)
    T_rect_c = np.eye(4)
    T_rect_c[:3, :3] = R
    result = EMVS(lens, depth_range=(1.0, 4.0), n_planes=100).run(fisheye_events, (times, T_w_rect @ T_rect_c))
    assert result.mask.mean() > 0.05
    assert abs(np.median(result.depth[result.mask]) / PLANE_DEPTH - 1) < 0.02
    # the poses taken as the rectified camera's (R left out) put a third of the map more than 5% off
    assert np.mean(np.abs(result.depth[result.mask] / PLANE_DEPTH - 1) < 0.05) > 0.75
    np.testing.assert_array_equal(result.K, pinhole.K)
