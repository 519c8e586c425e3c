"""EMVS fast path: batched image additions, one-pass argmax and median, vectorized transfers, the same DSI."""
from __future__ import annotations

import numpy as np
import pytest

from cmax import Camera, Events
from cmax.emvs import EMVS, DSI, semi_dense_depth
from cmax.emvs import gather as gather_module
from cmax.emvs.core import _groups, _packets
from cmax.emvs.dsi import (base_plane_homographies, plane_depths, plane_transfer, plane_transfers, project_packets,
                           splat_votes)
from cmax.emvs.gather import ShiftedAdditions, add_shifted, gather_votes
from cmax.emvs.result import plane_argmax
from cmax.geometry import interpolate_poses, invert_pose, se3_exp


# -- add_shifted: the additions, one after the other ------------------------------------------------
def _sequential_additions(dsi, images, plane, layer, offset):
    """``dsi[plane, y, x] += image[y + qy, x + qx]`` over the overlap, one addition after the other (numpy)."""
    _, height, width = dsi.shape
    for p, k, (qx, qy) in zip(plane, layer, offset):
        image = images[k]
        lo_x, lo_y = max(0, -qx), max(0, -qy)
        hi_x, hi_y = min(width, image.shape[1] - qx), min(height, image.shape[0] - qy)
        if hi_x > lo_x and hi_y > lo_y:
            dsi[p, lo_y:hi_y, lo_x:hi_x] += image[lo_y + qy: hi_y + qy, lo_x + qx: hi_x + qx]


def _random_additions(rng, n_planes=7, height=23, width=31, n_images=9, n_additions=60):
    shapes = [(int(rng.integers(5, 40)), int(rng.integers(5, 50))) for _ in range(n_images)]
    # Values of very different magnitudes: float32 sums depend on their order.
    images = [(rng.standard_normal(shape) * 10.0 ** rng.integers(-3, 4, shape)).astype(np.float32)
              for shape in shapes]
    plane = rng.integers(0, n_planes, n_additions)
    layer = rng.integers(0, n_images, n_additions)
    offset = rng.integers(-45, 45, (n_additions, 2))  # some additions miss the planes entirely
    start = np.concatenate([[0], np.cumsum([image.size for image in images])[:-1]])
    pool = np.concatenate([image.ravel() for image in images])
    base = rng.standard_normal((n_planes, height, width)).astype(np.float32)
    return images, pool, start, np.array(shapes), plane, layer, offset, base


@pytest.mark.parametrize("band_bytes", [1, 1 << 19])
def test_add_shifted_equals_the_additions_one_after_the_other(monkeypatch, band_bytes):
    monkeypatch.setattr(gather_module, "_BAND_BYTES", band_bytes)
    images, pool, start, shapes, plane, layer, offset, base = _random_additions(np.random.default_rng(1))
    expected = base.copy()
    _sequential_additions(expected, images, plane, layer, offset)
    out = base.copy()
    add_shifted(out, pool, start, shapes, plane, layer, offset)
    np.testing.assert_array_equal(out, expected)  # bit for bit: the same float32 sums in the same order
    assert not np.array_equal(out, base)


def test_add_shifted_refuses_what_it_cannot_read_or_write():
    images, pool, start, shapes, plane, layer, offset, base = _random_additions(np.random.default_rng(2))
    with pytest.raises(ValueError, match="float32"):
        add_shifted(base.astype(np.float64), pool, start, shapes, plane, layer, offset)
    with pytest.raises(ValueError, match="C-contiguous"):
        add_shifted(base[:, :, ::2], pool, start, shapes, plane, layer, offset)
    with pytest.raises(ValueError, match="pool must be"):
        add_shifted(base, pool.astype(np.float64), start, shapes, plane, layer, offset)
    with pytest.raises(ValueError, match="inside the pool"):
        add_shifted(base, pool[:-1], start, shapes, plane, layer, offset)  # the last image runs past the end
    with pytest.raises(ValueError, match="planes of the DSI"):
        add_shifted(base, pool, start, shapes, plane + base.shape[0], layer, offset)
    with pytest.raises(ValueError, match="images of the pool"):
        add_shifted(base, pool, start, shapes, plane, layer - 100, offset)


def test_shifted_additions_flush_when_their_buffer_is_full():
    rng = np.random.default_rng(3)
    images, _, _, _, plane, layer, offset, base = _random_additions(rng, n_images=4, n_additions=40)
    expected = base.copy()
    small = base.copy()
    pending = ShiftedAdditions(small, pool_floats=images[0].size)  # room for about one image at a time
    for chunk in np.array_split(np.arange(len(plane)), 4):
        _sequential_additions(expected, images, plane[chunk], layer[chunk], offset[chunk])
        room = pending.images(len(images), 50, 60)
        room[:] = 0.0
        for k, image in enumerate(images):
            room[k, :image.shape[0], :image.shape[1]] = image
        pending.add(plane[chunk], layer[chunk], offset[chunk])
    assert not np.array_equal(small, base)  # the buffer was full: earlier chunks were added already
    pending.flush()
    # Padding with zeros adds +0.0 beyond the images: the sums are unchanged.
    np.testing.assert_array_equal(small, expected)


# -- plane_argmax --------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_plane_argmax_equals_numpy_with_ties_and_nan(dtype):
    rng = np.random.default_rng(4)
    votes = rng.integers(0, 4, (9, 13, 17)).astype(dtype)  # many ties: the first maximum wins
    votes[5, 2, 3] = np.nan
    votes[0, 4, 4] = np.nan
    votes[:, 6, 7] = np.nan
    votes[:, 8, 9] = -np.inf
    index, maximum = plane_argmax(votes)
    expected = np.argmax(votes, axis=0)
    np.testing.assert_array_equal(index, expected)
    np.testing.assert_array_equal(maximum, np.take_along_axis(votes, expected[None], 0)[0].astype(np.float32))
    assert maximum.dtype == np.float32 and index.shape == (13, 17)


def test_plane_argmax_shapes():
    index, maximum = plane_argmax(np.arange(6, dtype=np.int32).reshape(1, 2, 3))  # integer votes: numpy path
    np.testing.assert_array_equal(index, 0)
    np.testing.assert_array_equal(maximum, np.arange(6).reshape(2, 3))
    with pytest.raises(ValueError, match="n_planes"):
        plane_argmax(np.zeros((0, 2, 3), np.float32))
    with pytest.raises(ValueError, match="n_planes"):
        plane_argmax(np.zeros((2, 3), np.float32))


# -- vectorized transfers and projection -----------------------------------------------------------
def _transfer_one_centre(centre, depths, K):
    """The affine transfer of one camera centre, written out plane by plane (independent of plane_transfers)."""
    cz = centre[2]
    valid = [z > cz + 1e-6 * abs(z) for z in depths]
    indices = [i for i, ok in enumerate(valid) if ok]
    if not indices:
        return None
    base = indices[len(indices) // 2]
    z_b = depths[base]
    scales, offsets = np.zeros(len(depths)), np.zeros((len(depths), 2))
    for i, z in enumerate(depths):
        lam = (z - cz) / (z_b - cz) if valid[i] else 0.0
        scales[i] = lam * z_b / z
        shift = (1.0 - lam) * np.asarray(centre[:2]) / z
        offsets[i] = (1.0 - scales[i]) * K[:2, 2] + K[:2, :2] @ shift
    return base, scales, offsets, np.array(valid)


def test_plane_transfers_of_many_centres_equal_one_by_one():
    K = np.array([[200.0, 0.5, 118.0], [0.0, 190.0, 92.0], [0.0, 0.0, 1.0]])
    depths = plane_depths((0.8, 6.0), 15)
    rng = np.random.default_rng(5)
    centres = rng.normal(0.0, 0.3, (12, 3))
    centres[3, 2] = 7.0   # behind every plane
    centres[4, 2] = 2.0   # in between: some planes only
    transfers = plane_transfers(centres, depths, K)
    assert len(transfers) == 12 and transfers[3] is None
    for centre, transfer in zip(centres, transfers):
        expected = _transfer_one_centre(centre, depths, K)
        if expected is None:
            continue
        assert transfer.base == expected[0]
        np.testing.assert_allclose(transfer.scales, expected[1], rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(transfer.offsets, expected[2], rtol=1e-12, atol=1e-9)
        np.testing.assert_array_equal(transfer.valid, expected[3])
    assert not transfers[4].valid.all() and transfers[4].valid.any()
    single = plane_transfer(centres[0], depths, K)
    np.testing.assert_array_equal(single.offsets, transfers[0].offsets)


def test_project_packets_with_packets_of_any_size():
    rng = np.random.default_rng(6)
    K = np.array([[150.0, 0, 60], [0, 150, 45], [0, 0, 1]])
    sizes = np.array([3, 7, 1, 5])
    poses = np.stack([se3_exp(np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3)]) for _ in sizes])
    H = base_plane_homographies(poses, np.array([1.5, 2.0, 2.5, 3.0]), K)
    pixels = rng.uniform([0, 0], [120, 90], (sizes.sum(), 2)).astype(np.float32)
    positions, hits = project_packets(pixels, H, sizes)
    packet = np.repeat(np.arange(len(sizes)), sizes)
    for i, (x, y) in enumerate(pixels.astype(np.float64)):
        u, v, w = H[packet[i]] @ [x, y, 1.0]
        assert hits[i] == (w > 0)
        np.testing.assert_allclose(positions[i], [u / w, v / w] if w > 0 else [u, v], rtol=1e-12)
    with pytest.raises(ValueError, match="packet"):
        project_packets(pixels, H, sizes + 1)


# -- EMVS.dsi: the same DSI as voting group by group -------------------------------------------------
def _events_and_trajectory(motion: str, n=40_000, width=96, height=72, seed=7):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 200_000, n))
    events = Events(rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n), width, height)
    times = np.linspace(0, 200_000, 41).round().astype(np.int64)
    s = np.linspace(-0.5, 0.5, len(times))
    twists = {"slide": [0.3, 0.02, 0.0, 0.0, 0.0, 0.0], "forward": [0.02, 0.01, 0.4, 0.0, 0.0, 0.0],
              "general": [0.2, -0.1, 0.15, 0.05, -0.08, 0.03]}[motion]
    poses = np.stack([se3_exp(np.asarray(twists) * si) for si in s])
    camera = Camera.from_intrinsics(80.0, 80.0, 47.5, 35.5, width, height)
    return events, camera, (times, poses)


def _dsi_group_by_group(emvs: EMVS, events, trajectory) -> np.ndarray:
    """EMVS's votes the way it voted before batching: each group on its own, its additions made at once."""
    times, T_w_c = trajectory
    t = events.t
    K, depths = emvs.camera.K, emvs.depths
    t_ref = (int(t[0]) + int(t[-1])) // 2
    T_w_ref = interpolate_poses(times, T_w_c, np.array([t_ref]))[0]
    starts, packet_t = _packets(t, emvs.events_per_pose)
    T_ref_c = invert_pose(T_w_ref) @ interpolate_poses(times, T_w_c, packet_t)
    centres = T_ref_c[:, :3, 3]
    inverse = 1.0 / depths
    cam = emvs.camera
    reach = max(K[0, 0], K[1, 1], K[0, 2], cam.width - K[0, 2], K[1, 2], cam.height - K[1, 2])
    max_travel = 2.0 * emvs.transfer_tolerance_px / (reach * 0.5 * (inverse[0] - inverse[-1]))
    sizes = np.diff(starts)
    pixels = cam.undistort(events)
    votes = np.zeros((len(depths), cam.height, cam.width), np.float32)
    for j, m in _groups(centres, sizes, emvs.events_per_transfer, max_travel):
        transfer = plane_transfer(np.average(centres[j:m], axis=0, weights=sizes[j:m]), depths, K)
        if transfer is None:
            continue
        H = base_plane_homographies(T_ref_c[j:m], depths[transfer.base], K)
        positions, hits = project_packets(pixels[starts[j]: starts[m]], H, sizes[j:m])
        if emvs.voting == "gather":
            gather_votes(votes, positions[hits], transfer, subpixel=emvs.subpixel)
        else:
            splat_votes(votes, positions[hits], transfer)
    return votes


@pytest.mark.parametrize("motion", ["slide", "forward", "general"])
def test_emvs_votes_equal_voting_group_by_group(monkeypatch, motion):
    # A small buffer makes the batched additions flush several times, also between warped groups.
    monkeypatch.setattr(gather_module, "_POOL_FLOATS", 3 * 96 * 72)
    events, camera, trajectory = _events_and_trajectory(motion)
    emvs = EMVS(camera, depth_range=(0.8, 6.0), n_planes=24, events_per_transfer=4096)
    dsi = emvs.dsi(events, trajectory)
    expected = _dsi_group_by_group(emvs, events, trajectory)
    assert expected.sum() > 0
    np.testing.assert_array_equal(dsi.votes, expected)
    # So the depth is the same as well.
    ours = semi_dense_depth(dsi)
    theirs = semi_dense_depth(DSI(expected, dsi.depths, dsi.K, dsi.t_ref_us, dsi.T_w_ref, dsi.n_events, 0.0,
                                  dsi.parallax_px))
    assert ours.mask.any()
    np.testing.assert_array_equal(ours.depth, theirs.depth)
    np.testing.assert_array_equal(ours.mask, theirs.mask)


def test_emvs_splat_voting_equals_group_by_group_too():
    events, camera, trajectory = _events_and_trajectory("general", n=8000)
    emvs = EMVS(camera, depth_range=(0.8, 6.0), n_planes=12, voting="splat", events_per_transfer=2048)
    np.testing.assert_array_equal(emvs.dsi(events, trajectory).votes, _dsi_group_by_group(emvs, events, trajectory))


# -- the median filter of the depth ----------------------------------------------------------------
@pytest.mark.parametrize("size", [3, 5])
def test_masked_median_equals_nanmedian_of_each_window(size):
    from cmax.emvs.result import _masked_median

    rng = np.random.default_rng(8)
    depth = rng.choice(plane_depths((0.5, 5.0), 30), (21, 27)).astype(np.float32)  # ties, as plane depths
    depth[:, :9] = rng.uniform(0.5, 5.0, (21, 9)).astype(np.float32)              # and distinct values
    mask = rng.random(depth.shape) < 0.45
    out = _masked_median(depth, mask, size)
    radius = size // 2
    expected = np.full(depth.shape, np.nan, np.float32)
    for r, c in zip(*np.nonzero(mask)):
        window = np.where(mask, depth, np.nan)[max(0, r - radius): r + radius + 1, max(0, c - radius): c + radius + 1]
        expected[r, c] = np.nanmedian(window)
    counts = [int(mask[max(0, r - radius): r + radius + 1, max(0, c - radius): c + radius + 1].sum())
              for r, c in zip(*np.nonzero(mask))]
    assert any(n % 2 == 0 for n in counts) and any(n % 2 == 1 for n in counts)  # both kinds of middle
    np.testing.assert_array_equal(out, expected)
    assert np.isnan(_masked_median(depth, np.zeros_like(mask), size)).all()


def _canvas_numpy(positions, transfer, width, height):
    """The canvas box written with numpy reductions (as the gather path computed it before)."""
    a = transfer.scales[transfer.valid]
    b = transfer.offsets[transfer.valid]
    reach_lo = np.min((-1.0 - b) / a[:, None], axis=0)
    reach_hi = np.max((np.array([width, height]) - b) / a[:, None], axis=0)
    lo = np.maximum(np.floor(positions.min(axis=0)), np.floor(reach_lo))
    hi = np.minimum(np.floor(positions.max(axis=0)) + 1, np.ceil(reach_hi))
    return None if np.any(hi < lo) else (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))


def test_canvas_box_equals_numpy_reductions():
    K = np.array([[100.0, 0, 60], [0, 100, 45], [0, 0, 1]])
    depths = plane_depths((1.0, 4.0), 20)
    rng = np.random.default_rng(9)
    boxes = []
    for trial in range(30):
        transfer = plane_transfer(rng.normal(0, 0.3, 3) * [1, 1, 0.5], depths, K)
        if transfer is None:
            continue
        spread = 10.0 ** rng.uniform(0, 3.5)  # from inside the image to far beyond what any plane sees
        centre = [60, 45] if trial % 3 else [60 + 2e4 * rng.choice([-1, 1]), 45]  # or where no plane sees
        positions = rng.normal(centre, spread, (int(rng.integers(1, 500)), 2))
        box = gather_module._canvas(positions, transfer, 120, 90)
        assert box == _canvas_numpy(positions, transfer, 120, 90)
        boxes.append(box)
    assert None in boxes and any(box is not None for box in boxes)
