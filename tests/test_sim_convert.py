"""Tests of video conversion (cmax/sim/convert.py), catalogues (cmax/sim/catalogue.py) and the CLI."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from cmax.cli import main
from cmax.io.h5 import read_h5
from cmax.sim.catalogue import load_catalogue, parse_catalogue, parse_shard, shard
from cmax.sim.convert import (
    ConvertSettings,
    VideoJob,
    collect_jobs,
    convert_collection,
    convert_video,
    load_manifest,
    merge_manifests,
)
from cmax.sim.esim import EsimSettings, EventSimulator

cv2 = pytest.importorskip("cv2")
FPS = 25


def write_video(path, n_frames=8, width=48, height=32, shift=0):
    """A small MJPG video of a moving smooth pattern; returns the decoded grey frames."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (width, height))
    assert writer.isOpened()
    y, x = np.mgrid[0:height, 0:width]
    for k in range(n_frames):
        value = 128 + 90 * np.sin(0.3 * (x - 2 * k - shift)) * np.cos(0.2 * y)
        writer.write(cv2.cvtColor(value.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    writer.release()
    capture, frames = cv2.VideoCapture(str(path)), []
    while True:
        ok, frame = capture.read()
        if not ok:
            return np.stack(frames)
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))


FAST = ConvertSettings(adaptive=False)


def test_converted_video_equals_simulate_on_the_same_frames(tmp_path):
    frames = write_video(tmp_path / "a.avi")
    times = np.arange(len(frames)) * (1_000_000 // FPS)
    result = convert_video(tmp_path / "a.avi", tmp_path / "a.h5", FAST, category="test")
    expected = EventSimulator().simulate(frames, times)
    events = read_h5(tmp_path / "a.h5")
    assert len(expected) > 100 and result.events == len(expected) and result.frames == len(frames)
    for name in "xytp":
        np.testing.assert_array_equal(getattr(events, name), getattr(expected, name))
    assert result.status == "ok" and result.duration_s == pytest.approx(times[-1] * 1e-6)
    assert not list(tmp_path.glob("*.partial")) and not list(tmp_path.glob("*.lock"))


def test_adaptive_conversion_and_time_range(tmp_path):
    write_video(tmp_path / "a.avi", n_frames=6)
    settings = ConvertSettings(adaptive=True, method="linear", t0_s=0.04, t1_s=0.12)
    result = convert_video(tmp_path / "a.avi", tmp_path / "a.h5", settings)
    assert result.frames == 2 and result.samples > result.frames and result.events > 0  # 40, 80 ms
    assert result.capped_intervals == 0
    events = read_h5(tmp_path / "a.h5")
    assert 40_000 <= events.t[0] and events.t[-1] <= 80_000


def test_collection_with_a_corrupt_video_and_resume(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    write_video(videos / "a.avi")
    write_video(videos / "b.avi", shift=3)
    (videos / "c.mp4").write_bytes(b"not a video at all")
    jobs, missing = collect_jobs(videos)
    assert [job.name for job in jobs] == ["a", "b", "c"] and missing == []
    out = tmp_path / "out"
    manifest = convert_collection(jobs, out, FAST, progress=False)
    assert {n: v["status"] for n, v in manifest["videos"].items()} == {"a": "ok", "b": "ok", "c": "failed"}
    assert "DecodeError" in manifest["videos"]["c"]["error"] and "c.mp4" in manifest["videos"]["c"]["error"]
    assert load_manifest(out / "manifest.json") == manifest
    assert manifest["totals"]["ok"] == 2 and not (out / "c.h5").exists()
    stat_a, bytes_a = (out / "a.h5").stat().st_mtime_ns, (out / "a.h5").read_bytes()
    (out / "b.h5").unlink()  # a crash: the output is missing
    (out / "b.h5.0123456789abcdef.partial").write_bytes(b"half")  # left by a killed writer
    seen = []
    convert_collection(jobs, out, FAST, progress=False, on_result=lambda r: seen.append(r.name))
    assert seen == ["b", "c"]  # a skipped, b redone, c retried
    assert (out / "a.h5").stat().st_mtime_ns == stat_a and (out / "a.h5").read_bytes() == bytes_a
    assert (out / "b.h5").is_file() and not list(out.glob("*.partial"))
    with pytest.raises(ValueError, match="other settings"):
        convert_collection(jobs, out, ConvertSettings(adaptive=False, lam=0.3), progress=False)


def test_other_settings_are_named_key_by_key(tmp_path):
    """The refusal printed only the recorded dict; it names each differing key, recorded vs now."""
    write_video(tmp_path / "a.avi")
    jobs, _ = collect_jobs(tmp_path / "a.avi")
    convert_collection(jobs, tmp_path / "out", FAST, progress=False)
    other = ConvertSettings(EsimSettings(cp=0.3), adaptive=False, size=(48, 32))
    with pytest.raises(ValueError) as error:
        convert_collection(jobs, tmp_path / "out", other, progress=False)
    message = str(error.value)
    assert "other settings (esim.cp: 0.2 (recorded) vs 0.3 (now), size: None (recorded) vs [48, 32] (now))" in message
    assert "lam" not in message


def test_parallel_workers_and_list_file(tmp_path):
    write_video(tmp_path / "a.avi")
    write_video(tmp_path / "b.avi", shift=5)
    (tmp_path / "list.txt").write_text("a.avi\tNatural\n# comment\nb.avi\tDriving\n")
    jobs, _ = collect_jobs(tmp_path / "list.txt")
    assert [(j.name, j.category) for j in jobs] == [("a", "Natural"), ("b", "Driving")]
    manifest = convert_collection(jobs, tmp_path / "out", FAST, workers=2, progress=False)
    assert [v["category"] for v in manifest["videos"].values()] == ["Natural", "Driving"]
    single = convert_video(tmp_path / "a.avi", tmp_path / "single.h5", FAST)
    assert manifest["videos"]["a"]["events"] == single.events


def test_catalogue_parsing_and_shards(tmp_path):
    entries = load_catalogue("slowtv")
    assert len(entries) == 40 and entries[0].name == "00000"
    assert {e.category.split("-")[0] for e in entries} == {"Natural", "Underwater", "Driving"}
    shards = [shard(entries, i, 3) for i in range(3)]
    names = [e.name for part in shards for e in part]
    assert sorted(names) == [e.name for e in entries] and len(set(names)) == 40
    assert parse_shard("2/4") == (2, 4)
    for bad in ("4/4", "-1/2", "1", "a/b", "0/0"):
        with pytest.raises(ValueError):
            parse_shard(bad)
    with pytest.raises(ValueError, match="header"):
        parse_catalogue("0\turl\tNatural\n")
    with pytest.raises(ValueError, match="repeated"):
        parse_catalogue("index\turl\tcategory\n0\tu\tA\n0\tv\tB\n")
    with pytest.raises(ValueError, match="unknown catalogue"):
        load_catalogue("nope")
    write_video(tmp_path / "00001.avi")
    jobs, missing = collect_jobs(tmp_path, catalogue="slowtv", shard=(1, 2))
    assert [(j.name, j.category) for j in jobs] == [("00001", entries[1].category)]
    assert len(missing) == 19 and "00003" in missing and "00000" not in missing


def test_manifest_merge_and_cli(tmp_path, capsys):
    write_video(tmp_path / "00000.avi")
    write_video(tmp_path / "00001.avi", shift=2)
    outs = []
    for i in range(2):
        out = tmp_path / f"shard{i}"
        status = main(["simulate", str(tmp_path), "-o", str(out), "--catalogue", "slowtv",
                       "--shard", f"{i}/2", "--no-adaptive", "--quiet"])
        assert status == 0
        outs.append(out / "manifest.json")
    assert list(load_manifest(outs[1])["videos"]) == ["00001"]
    assert main(["manifest", "merge", *map(str, outs), "-o", str(tmp_path / "all.json")]) == 0
    merged = json.loads((tmp_path / "all.json").read_text())
    assert list(merged["videos"]) == ["00000", "00001"] and len(merged["missing"]) == 38
    assert merged["totals"]["ok"] == 2 and merged["simulator_version"]
    other = dict(load_manifest(outs[0]), settings={"different": True})
    with pytest.raises(ValueError, match="settings"):
        merge_manifests([other, load_manifest(outs[1])])
    assert main(["simulate", str(tmp_path / "00000.avi"), "-o", str(tmp_path / "one.h5"),
                 "--no-adaptive"]) == 0
    assert "events from 8 frames" in capsys.readouterr().out


def test_bad_inputs_give_clear_errors(tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match="input not found"):
        collect_jobs(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="video not found"):
        convert_video(tmp_path / "missing.mp4", tmp_path / "x.h5", FAST)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no videos"):
        collect_jobs(tmp_path / "empty")
    write_video(tmp_path / "a.avi")
    with pytest.raises(ValueError, match="zero frames"):
        convert_video(tmp_path / "a.avi", tmp_path / "x.h5", ConvertSettings(adaptive=False, t0_s=50.0))
    assert not (tmp_path / "x.h5").exists() and not list(tmp_path.glob("x.h5*"))
    with pytest.raises(ValueError, match="no frames"):
        convert_video("none.mp4", tmp_path / "x.h5", FAST, frames=iter(()))
    with pytest.raises(ValueError, match="cp must be"):
        EsimSettings(cp=0.0)
    with pytest.raises(ValueError, match="t1_s"):
        ConvertSettings(t0_s=2.0, t1_s=1.0)
    assert main(["simulate", str(tmp_path / "a.avi"), "-o", str(tmp_path / "x.h5"), "--cn", "-1"]) == 2
    assert "cn must be" in capsys.readouterr().err
    with pytest.raises(ValueError, match="workers"):
        convert_collection([VideoJob("a", tmp_path / "a.avi")], tmp_path / "o", FAST, workers=0)


def test_every_bad_video_is_reported_and_the_others_convert(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    write_video(videos / "a.avi")
    writer = cv2.VideoWriter(str(videos / "empty.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (48, 32))
    writer.release()  # a valid container with zero frames
    write_video(videos / "long.avi", n_frames=40)
    (videos / "cut.avi").write_bytes((videos / "long.avi").read_bytes()[:20_000])  # truncated
    (videos / "long.avi").unlink()
    (videos / "text.mp4").write_text("not a video")
    jobs, _ = collect_jobs(videos)
    out = tmp_path / "out"
    manifest = convert_collection(jobs, out, FAST, progress=False, workers=2)
    videos_ = manifest["videos"]
    assert videos_["a"]["status"] == "ok" and (out / "a.h5").is_file()
    for name, message in (("empty", "decoded no frame"), ("cut", "truncated or corrupt"),
                          ("text", "cannot decode")):
        assert videos_[name]["status"] == "failed", name
        assert message in videos_[name]["error"] and name in videos_[name]["error"]
        assert not (out / f"{name}.h5").exists()
    assert manifest["totals"] == {**manifest["totals"], "ok": 1, "failed": 3}
    assert sorted(p.name for p in out.iterdir()) == ["a.h5", "manifest.json"]  # nothing partial


@pytest.mark.parametrize("adaptive", [False, True])
def test_bad_frames_given_to_a_conversion_leave_no_file(tmp_path, adaptive):
    frames = write_video(tmp_path / "a.avi", n_frames=3).astype(np.float32)
    settings = ConvertSettings(adaptive=adaptive, method="linear")
    cases = {
        "increas": [(frames[0], 0), (frames[1], 40_000), (frames[2], 40_000)],  # non-increasing
        "shape": [(frames[0], 0), (frames[1][:, :40], 40_000)],  # mismatched sizes
        r"\[0, 255\]": [(frames[0], 0), (frames[1] * 3, 40_000)],
    }
    for message, items in cases.items():
        with pytest.raises(ValueError, match=message):
            convert_video(tmp_path / "a.avi", tmp_path / "x.h5", settings, frames=iter(items))
        assert not (tmp_path / "x.h5").exists() and not list(tmp_path.glob("x.h5*"))


def test_settings_reject_bad_values():
    for kwargs, name in (({"cp": 0.0}, "cp"), ({"cn": -0.2}, "cn"), ({"cp": float("nan")}, "cp")):
        with pytest.raises(ValueError, match=name):
            EsimSettings(**kwargs)
    for kwargs, name in (({"lam": 0}, "lam"), ({"method": "cubic"}, "method"),
                         ({"size": (0, 10)}, "size"), ({"t0_s": -1.0}, "t0_s")):
        with pytest.raises(ValueError, match=name):
            ConvertSettings(**kwargs)


def test_convert_video_does_not_replace_an_existing_file_unless_told(tmp_path):
    write_video(tmp_path / "a.avi")
    (tmp_path / "a.h5").write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="pass overwrite=True"):
        convert_video(tmp_path / "a.avi", tmp_path / "a.h5", FAST)
    assert (tmp_path / "a.h5").read_bytes() == b"precious" and not list(tmp_path.glob("a.h5.*"))
    result = convert_video(tmp_path / "a.avi", tmp_path / "a.h5", FAST, overwrite=True)
    assert len(read_h5(tmp_path / "a.h5")) == result.events > 0


def test_a_16_bit_image_sequence_is_simulated_on_its_own_values(tmp_path, capsys):
    """Was: rounded to 8 bits (5,376 events of 6,144 here: 16-bit 200 and 350 both became grey 1), and read
    as floats a dark 16-bit frame drew `frames are floats in [0.778, 0.778]: ... multiply it by 255`."""
    folder = tmp_path / "render"
    folder.mkdir()
    values = 200 + 150 * np.arange(8)  # uniform 16-bit frames, grey 0.78 .. 4.9 of 255
    for i, value in enumerate(values):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((6, 8), value, np.uint16))
    (folder / "timestamps.txt").write_text("".join(f"{0.01 * i:.2f}\n" for i in range(8)))
    # independent: L = log(v / 65535 + eps) rises through levels L0 + k C; each crossing at the linear
    # interpolation of L between the two frames around it
    level = np.log(values / 65535 + 1e-3)
    crossings = np.arange(1, int((level[-1] - level[0]) / 0.2) + 1) * 0.2 + level[0]
    assert np.all(np.abs((crossings - level[0]) / 0.2 - np.rint((crossings - level[0]) / 0.2)) < 1e-9)
    index = np.searchsorted(level, crossings) - 1
    expected_t = np.rint(1e4 * (index + (crossings - level[index]) / (level[index + 1] - level[index])))
    assert expected_t.size == 8 and ((level[-1] - level[0]) / 0.2) % 1 > 0.001  # not on a level
    settings = ConvertSettings(adaptive=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = convert_video(folder, tmp_path / "render.h5", settings)
    events = read_h5(tmp_path / "render.h5")
    assert result.events == len(events) == 8 * 6 * 8 and events.p.all()
    np.testing.assert_array_equal(np.unique(events.t), expected_t)
    assert main(["simulate", str(folder), "-o", str(tmp_path / "cli" / "render.h5"), "--no-adaptive",
                 "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert len(read_h5(tmp_path / "cli" / "render.h5")) == 384


def test_merging_manifests_of_other_settings_names_the_files_and_the_keys(tmp_path, capsys):
    """Was: `manifests differ in 'settings': {'esim': {...}, 'size': None, ...} vs {...}`, both tables whole
    and neither file named."""
    write_video(tmp_path / "a.avi")
    write_video(tmp_path / "b.avi", shift=3)
    assert main(["simulate", str(tmp_path / "a.avi"), "-o", str(tmp_path / "s0" / "a.h5"), "--no-adaptive",
                 "--quiet"]) == 0
    assert main(["simulate", str(tmp_path / "b.avi"), "-o", str(tmp_path / "s1" / "b.h5"), "--no-adaptive",
                 "--quiet", "--cp", "0.5"]) == 0
    capsys.readouterr()
    one, two = tmp_path / "s0" / "manifest.json", tmp_path / "s1" / "manifest.json"
    assert main(["manifest", "merge", str(one), str(two), "-o", str(tmp_path / "all.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"cmax manifest: error: {two} differs from {one} in 'settings' (esim.cp: 0.2 ({one}) vs 0.5 "
                   f"({two})): merge only conversions made with the same settings and simulator")
    assert not (tmp_path / "all.json").exists()
    with pytest.raises(ValueError, match=r"^manifest 2 differs from manifest 1 in 'settings' \(esim.cp: 0.2 "):
        merge_manifests([load_manifest(one), load_manifest(two)])


def test_each_video_of_a_collection_gets_noise_of_its_own_reproducibly(tmp_path):
    """Was: every video of a conversion seeded its simulator with the same --seed, so two still videos of one size
    got byte-identical shot noise (a pattern a network can learn across a data set). Each video's seed now comes
    from the collection's seed and its name (``video_seed``): the two differ, a rerun is identical, and
    ``convert_video`` with the settings the h5 file records reproduces it; ``seed_per_video=False`` gives the
    shared seed (and the manifest settings of before); settings whose events do not depend on the seed read as
    before."""
    from cmax.sim.convert import video_seed

    still = np.full((4, 32, 48), 128, np.uint8)
    for name in ("a", "b"):
        writer = cv2.VideoWriter(str(tmp_path / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (48, 32))
        for frame in still:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
        writer.release()
    (tmp_path / "videos").mkdir()
    for name in ("a", "b"):
        (tmp_path / f"{name}.avi").rename(tmp_path / "videos" / f"{name}.avi")
    jobs, _ = collect_jobs(tmp_path / "videos")
    noisy = ConvertSettings(EsimSettings(seed=7, shot_noise_rate_hz=20.0), adaptive=False)
    assert noisy.to_dict()["seed_per_video"] is True and "seed_per_video" not in FAST.to_dict()
    convert_collection(jobs, tmp_path / "own", noisy, progress=False)
    a, b = read_h5(tmp_path / "own" / "a.h5"), read_h5(tmp_path / "own" / "b.h5")
    assert len(a) > 20 and len(b) > 20 and not (len(a) == len(b) and np.array_equal(a.x, b.x))
    convert_collection(jobs, tmp_path / "again", noisy, progress=False)
    assert read_h5(tmp_path / "again" / "a.h5") == a and read_h5(tmp_path / "again" / "b.h5") == b
    import h5py

    with h5py.File(tmp_path / "own" / "a.h5") as file:
        recorded = json.loads(file.attrs["settings"])
    assert recorded["esim"]["seed"] == video_seed(7, "a") != 7 and "seed_per_video" not in recorded
    alone = ConvertSettings(EsimSettings(**recorded["esim"]), adaptive=False)
    convert_video(tmp_path / "videos" / "a.avi", tmp_path / "alone.h5", alone)
    assert read_h5(tmp_path / "alone.h5") == a
    shared = ConvertSettings(EsimSettings(seed=7, shot_noise_rate_hz=20.0), adaptive=False, seed_per_video=False)
    convert_collection(jobs, tmp_path / "shared", shared, progress=False)
    assert read_h5(tmp_path / "shared" / "a.h5").t.tolist() == read_h5(tmp_path / "shared" / "b.h5").t.tolist()
    assert "seed_per_video" not in load_manifest(tmp_path / "shared" / "manifest.json")["settings"]
    # a collection converted before per-video seeds (its settings lack the key) is not resumed with them
    with pytest.raises(ValueError, match=r"seed_per_video: 'absent' \(recorded\) vs True \(now\)"):
        convert_collection(jobs, tmp_path / "shared", noisy, progress=False)
