"""Calibration files are read by the library (:mod:`cmax.io.calibration`), not by the command line."""
from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import MVSEC_LEFT_CAMCHAIN as CAMCHAIN  # noqa: E402


def test_a_camchain_is_read_by_the_library_without_the_command_line(tmp_path: Path) -> None:
    """``cmax.io.read_calibration`` reads a Kalibr camchain, and ``learned.data``'s MVSEC camera is built from it,
    without importing ``cmax.cli`` (was: the parser lived in ``cmax.cli.recording``, which learned.data imported)."""
    path = tmp_path / "camchain.yaml"
    path.write_text(CAMCHAIN)
    script = textwrap.dedent(f"""
        import sys
        import cmax.io
        from learned.data import _mvsec_camera
        calibration = cmax.io.read_calibration({str(path)!r}, "cam0")
        camera = _mvsec_camera({str(path)!r}, "cam0", 346, 260)
        print(calibration.model, calibration.size, camera.model, sorted(m for m in sys.modules if m.startswith("cmax.cli")))
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["equidistant", "(346,", "260)", "equidistant", "[]"]


def test_the_calibration_s_camera_undistorts_as_opencv_s_fisheye_with_its_rectification(tmp_path: Path) -> None:
    """:meth:`cmax.io.Calibration.camera` of a rectified fisheye camchain maps pixels where
    ``cv2.fisheye.undistortPoints(..., R=R_rect, P=P_rect)`` does (an independent implementation)."""
    from cmax.io import read_calibration

    path = tmp_path / "camchain.yaml"
    path.write_text(CAMCHAIN)
    calibration = read_calibration(path, "cam0")
    camera = calibration.camera(346, 260)
    pixels = np.array([[10.0, 12.0], [173.0, 133.0], [300.0, 240.0], [50.0, 200.0]])
    expected = cv2.fisheye.undistortPoints(pixels.reshape(-1, 1, 2), calibration.K, calibration.distortion,
                                           R=calibration.rectification, P=calibration.rectified_K).reshape(-1, 2)
    np.testing.assert_allclose(camera.undistort_points(pixels), expected, atol=1e-3)
    np.testing.assert_array_equal(camera.pinhole_K, calibration.rectified_K)


ROS_CAMERA_INFO = """image_width: 346
image_height: 260
camera_name: davis
camera_matrix:
  rows: 3
  cols: 3
  data: [226.38, 0, 173.64, 0, 226.15, 133.73, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.048, 0.012, 0.0003, -0.0001, 0.001]
"""

ECD_CALIB = "199.092366542 198.82882047 132.192071378 110.712660011 -0.368436311798 0.150947243557 " \
            "-0.000296130534385 -0.000759431726241 0.0"


def test_a_byte_order_mark_changes_nothing(tmp_path: Path) -> None:
    """A calibration file saved with a UTF-8 byte order mark (Windows editors) reads as the same file without it,
    in each format (was: a ROS camera_info's first key, ``image_width``, read as '\\ufeffimage_width', so its size was
    silently dropped and never checked against the events'; a camchain's first camera was not found ('cameras
    found: cam1, \\ufeffcam0'); an ECD calib.txt was refused as malformed)."""
    from cmax.io import read_calibration

    for name, text, camera in [("camera_info.yaml", ROS_CAMERA_INFO, "cam0"), ("camchain.yaml", CAMCHAIN, "cam0"),
                               ("calib.txt", ECD_CALIB + "\n", "cam0")]:
        plain, marked = tmp_path / name, tmp_path / f"bom_{name}"
        plain.write_text(text)
        marked.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
        expected, got = read_calibration(plain, camera), read_calibration(marked, camera)
        np.testing.assert_array_equal(got.K, expected.K)
        np.testing.assert_array_equal(got.distortion, expected.distortion)
        assert got.size == expected.size
        assert got.model == expected.model
    assert read_calibration(tmp_path / "bom_camera_info.yaml").size == (346, 260)     # the file's own numbers
    np.testing.assert_array_equal(read_calibration(tmp_path / "bom_calib.txt").K[0, [0, 2]],
                                  [199.092366542, 132.192071378])


def test_a_comment_after_the_numbers_of_a_calib_txt_is_ignored(tmp_path: Path) -> None:
    """``fx fy cx cy k1 k2 p1 p2 k3  # DAVIS240C`` reads as the nine numbers (was: refused, 'expected one line
    fx fy cx cy [k1 k2 p1 p2 [k3]]', of a line that is one)."""
    from cmax.io import read_calibration

    path = tmp_path / "calib.txt"
    path.write_text("# ECD slider_depth\n" + ECD_CALIB + "   # fx fy cx cy k1 k2 p1 p2 k3\n")
    calibration = read_calibration(path)
    numbers = [float(v) for v in ECD_CALIB.split()]
    np.testing.assert_array_equal(calibration.K[[0, 1, 0, 1], [0, 1, 2, 2]], numbers[:4])
    np.testing.assert_array_equal(calibration.distortion, numbers[4:])


def test_a_hash_inside_quotes_or_a_word_is_not_a_comment(tmp_path: Path) -> None:
    """YAML's comment starts at a ``#`` after a space and outside quotes: a camchain's ``rostopic: "/dvs #2/left/
    image_raw"`` is that topic, ``rostopic: /dvs#2/left/image_raw`` too (were: cut at the ``#``, to ``"/dvs`` and
    ``/dvs``: the camera's side lost); a comment after a quoted value is still dropped, and so are whole-line
    comments."""
    from cmax.io import read_calibration
    from cmax.io.calibration import topic_side

    for written, expected in (('"/dvs #2/left/image_raw"  # the left DAVIS', "/dvs #2/left/image_raw"),
                              ("'/dvs #2/left/image_raw' # it's the left one", "/dvs #2/left/image_raw"),
                              ("/dvs#2/left/image_raw   # plain", "/dvs#2/left/image_raw")):
        path = tmp_path / "camchain.yaml"
        path.write_text("# a camchain\n" + CAMCHAIN.replace("rostopic: /davis/left/image_raw", f"rostopic: {written}"))
        calibration = read_calibration(path, "cam0")
        assert calibration.topic == expected and topic_side(calibration.topic) == "left", written
        np.testing.assert_array_equal(calibration.K[0, [0, 2]], [226.38018519795807, 173.6470807871759])


def test_yaml_quoting_and_escapes_are_read_as_yaml_reads_them(tmp_path: Path) -> None:
    """Quoted keys and escapes in double-quoted values are YAML's own: ``'distortion_model': equidistant`` was read as
    a key with its quotes, so the camera fell back to radtan and its fisheye coefficients were applied as radtan ones
    without a word; ``rostopic: "/davis/\\x6ceft/image_raw"`` kept its escape (no side: the check of which camera of
    the rig it is was skipped); ``'it''s'`` kept both quotes; a ``[`` inside a quoted topic swallowed the lines after
    it (the rectification and projection lost). Each reads as the plain file does."""
    from cmax.io import read_calibration

    plain = tmp_path / "plain.yaml"
    plain.write_text(CAMCHAIN)
    expected = read_calibration(plain, "cam0")
    topic = "rostopic: /davis/left/image_raw"
    for name, text, topic_read in [
        ("quoted_keys", CAMCHAIN.replace("cam0:", '"cam0":').replace("distortion_model:", "'distortion_model':"),
         "/davis/left/image_raw"),
        ("escaped", CAMCHAIN.replace(topic, 'rostopic: "/davis/\\x6ceft/image_raw"').replace(
            "distortion_model: equidistant", 'distortion_model: "equi\\u0064istant"'), "/davis/left/image_raw"),
        ("doubled_quote", CAMCHAIN.replace(topic, "rostopic: '/davis/left/it''s'"), "/davis/left/it's"),
        ("bracket_quoted", CAMCHAIN.replace(topic, 'rostopic: "/davis[0]/left/image_raw["'),
         "/davis[0]/left/image_raw["),
    ]:
        path = tmp_path / f"{name}.yaml"
        path.write_text(text)
        got = read_calibration(path, "cam0")
        assert got.model == "equidistant" and got.topic == topic_read, name
        for field in ("K", "distortion", "rectification", "rectified_K"):
            np.testing.assert_array_equal(getattr(got, field), getattr(expected, field), err_msg=f"{name}: {field}")


def test_yaml_this_reader_does_not_read_is_refused_naming_the_file_and_line(tmp_path: Path) -> None:
    """What the YAML reader cannot read is refused naming the file and line (were: a merge key ``<<: *cam0`` gave
    cam1 without cam0's fisheye distortion (radtan, no distortion, no size); a second document's numbers overrode the
    first's; a block scalar ``rostopic: >`` read as the topic '>'; a value going on over lines cut; a key given twice
    read as the last; an anchor or alias, a flow mapping or tabs: refused as 'no intrinsics/cam0 (cameras found:
    none)' or misread by the count of a tab as one space). A trailing ``---`` (as ``rostopic echo`` ends a message)
    and a leading ``%YAML`` / ``---`` are read."""
    from cmax.io import read_calibration

    cam1 = ("cam1:\n  <<: *c0\n  intrinsics: [200.0, 200.0, 170.0, 130.0]\n"
            "  rostopic: /davis/right/image_raw\n")
    topic = "rostopic: /davis/left/image_raw"
    cases = [
        ("merge", CAMCHAIN + cam1, "cam1", r"line 23: merge keys \('<<: \*c0'\) are not read"),
        ("anchor", CAMCHAIN.replace("cam0:", "cam0: &c0"), "cam0", r"line 1: '&c0': anchors \(&name\) are not read"),
        ("alias", CAMCHAIN.replace("distortion_model: equidistant", "distortion_model: *m"), "cam0",
         r"line 10: '\*m': aliases"),
        ("two_documents", "---\n" + CAMCHAIN + "---\n" + CAMCHAIN.replace("226.38018519795807", "100.0"), "cam0",
         r"line 24: a second YAML document begins after line 23"),
        ("block_scalar", CAMCHAIN.replace(topic, "rostopic: >\n    /davis/left/image_raw"), "cam0",
         r"line 13: '>': block scalars"),
        ("over_lines", CAMCHAIN.replace(topic, 'rostopic: "/davis/left/\n    image_raw"'), "cam0",
         r"line 13: the quoted value '\"/davis/left/' goes on over lines"),
        ("plain_over_lines", CAMCHAIN.replace(topic, "rostopic: /davis/left/\n    image_raw"), "cam0",
         r"line 14: 'image_raw' is neither 'key: value' nor '- item'"),
        ("twice", CAMCHAIN.replace("distortion_model: equidistant", "distortion_model: equidistant\n"
                                   "  distortion_model: radtan"), "cam0",
         r"line 11: the key 'distortion_model' is given a second time"),
        ("flow_mapping", "cam0: {camera_model: pinhole, intrinsics: [226.4, 226.2, 173.6, 133.7]}\n", "cam0",
         r"line 1: .*flow mappings \{key: value, \.\.\.\} are not read"),
        ("tabs", CAMCHAIN.replace("\n  distortion_model", "\n\tdistortion_model"), "cam0",
         r"line 10 is indented with a tab"),
        ("unclosed", CAMCHAIN.replace("intrinsics: [226.38018519795807,", "intrinsics: [[226.38018519795807,"), "cam0",
         r"line 11: a '\[' is never closed"),
    ]
    for name, text, camera, message in cases:
        path = tmp_path / f"{name}.yaml"
        path.write_text(text)
        with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: {message}"):
            read_calibration(path, camera)
    framed = tmp_path / "framed.yaml"
    framed.write_text("%YAML 1.2\n---\n" + CAMCHAIN + "---\n")
    np.testing.assert_array_equal(read_calibration(framed, "cam0").distortion,
                                  [-0.048031442223833355, 0.011330957517194437, -0.055378166304281135,
                                   0.021500973881459395])


def test_dsec_s_rectify_map_or_an_event_file_given_as_calibration_names_the_file_to_give(tmp_path: Path,
                                                                                         capsys) -> None:
    """``--calib SEQ/events/left/rectify_map.h5`` (DSEC's rectify map, the file a DSEC user knows) was parsed as
    text and refused with "expected one line 'fx fy cx cy [k1 k2 p1 p2 [k3]]' (ECD calib.txt)", which points the
    wrong way: it now names the sequence's cam_to_cam.yaml; any other HDF5 or binary file is called what it is."""
    import h5py
    import pytest

    from cmax.cli import main
    from cmax.events import Events
    from cmax.io import read_calibration, write_h5

    left = tmp_path / "zurich_city_00_a" / "events" / "left"
    left.mkdir(parents=True)
    (tmp_path / "zurich_city_00_a" / "calibration").mkdir()
    yaml = tmp_path / "zurich_city_00_a" / "calibration" / "cam_to_cam.yaml"
    yaml.write_text("intrinsics:\n  camRect0:\n    camera_matrix: [60.0, 60.0, 32.0, 24.0]\n    resolution: [64, 48]\n")
    with h5py.File(left / "rectify_map.h5", "w") as file:
        file["rectify_map"] = np.zeros((48, 64, 2), np.float32)
    with pytest.raises(ValueError, match="rectify map") as error:
        read_calibration(left / "rectify_map.h5")
    assert f"cam_to_cam.yaml ({yaml.resolve()})" in str(error.value)
    assert "ECD calib.txt)" not in str(error.value).split(":")[0]
    rng = np.random.default_rng(0)
    events = Events(rng.integers(0, 64, 200), rng.integers(0, 48, 200), np.sort(rng.integers(0, 10_000, 200)),
                    rng.integers(0, 2, 200), 64, 48)
    write_h5(tmp_path / "events.h5", events)
    with pytest.raises(ValueError, match=r"events\.h5 is an HDF5 file, not a calibration file: expected ECD"):
        read_calibration(tmp_path / "events.h5")
    (tmp_path / "blob.bin").write_bytes(b"% header\n" + bytes(16))
    with pytest.raises(ValueError, match=r"blob\.bin is a binary file, not a calibration file"):
        read_calibration(tmp_path / "blob.bin")
    # the command line: exit 2, one line naming the yaml to pass
    assert main(["fit", str(tmp_path / "events.h5"), "--calib", str(left / "rectify_map.h5"), "-o",
                 str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pass the sequence's cam_to_cam.yaml" in err and str(yaml.resolve()) in err
    # a calibration that is text is still read as before
    assert read_calibration(yaml, "camRect0").K[0, 0] == 60.0
