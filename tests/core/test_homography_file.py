"""Camera homography files: JSON or YAML, 3x3 or 9 numbers; errors name the file and the key."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import Homography, homography_from_pose
from drvs.core.homography_file import load_homography, save_homography

ROWS = [[0.5, -0.25, 4.0], [0.0, 2.0, -1.0], [0.001, 0.002, 1.0]]
FLAT = [v for row in ROWS for v in row]
EXPECTED = np.asarray(ROWS) / 4.0  # scaled so that the largest entry has magnitude 1


def in_file(path: Path) -> str:
    """A regex matching the start of an error about this file."""
    return "^" + re.escape(f"homography file {path}")


def test_json_3x3(tmp_path: Path) -> None:
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"homography": ROWS, "camera_id": "cam1"}))
    h = load_homography(path)
    assert np.array_equal(h.matrix, EXPECTED)


def test_json_flat_nine(tmp_path: Path) -> None:
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"homography": FLAT}))
    assert np.array_equal(load_homography(str(path)).matrix, EXPECTED)


def test_yaml_3x3(tmp_path: Path) -> None:
    path = tmp_path / "cam.yaml"
    path.write_text(
        "# calibrated 2026-11-20\n"
        "homography:\n"
        "  - [0.5, -0.25, 4]\n"
        "  - [0, 2, -1]\n"
        "  - [0.001, 0.002, 1]\n"
        "image_size: [640, 480]\n"
    )
    assert np.array_equal(load_homography(path).matrix, EXPECTED)


def test_yaml_flat_nine(tmp_path: Path) -> None:
    path = tmp_path / "cam.yml"
    path.write_text("homography: [0.5, -0.25, 4, 0, 2, -1, 0.001, 0.002, 1]\n")
    assert np.array_equal(load_homography(path).matrix, EXPECTED)


def test_save_load_round_trip(tmp_path: Path) -> None:
    h = homography_from_pose((2.0, -1.0, 2.7), 120.0, 35.0, 70.0, (1280, 720))
    path = tmp_path / "cam.homography.yaml"
    save_homography(path, h, camera_id="cam7", image_size=[1280, 720])
    data = yaml.safe_load(path.read_text())
    assert data["camera_id"] == "cam7"
    assert data["image_size"] == [1280, 720]
    assert len(data["homography"]) == 3
    back = load_homography(path)
    assert np.array_equal(back.matrix, h.matrix)
    assert back.to_list() == h.to_list()
    # The mapping is unchanged.
    assert np.array_equal(back.apply([[640.0, 360.0]]), h.apply([[640.0, 360.0]]))


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(InvalidArgument, match=in_file(path) + ": No such file"):
        load_homography(path)


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgument, match=in_file(tmp_path) + ": Is a directory"):
        load_homography(tmp_path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", r": no 'homography' key"),
        ("{}", r": no 'homography' key"),
        ('{"homograph": [1, 0, 0, 0, 1, 0, 0, 0, 1]}', r": no 'homography' key"),
        ("matrix:\n  - [1, 0, 0]\n", r": no 'homography' key"),
        ("[1, 0, 0, 0, 1, 0, 0, 0, 1]", r": no 'homography' key"),
        ("just some text", r": no 'homography' key"),
        ("homography: [1, 0, 0", r": not JSON or YAML"),
        ('{"homography": [1, 0, 0,', r": not JSON or YAML"),
        ("homography: [[1, 0, 0], [0, 1, 0], [0, 0]]", r": 'homography' must be 3 rows of 3 numbers"),
        ("homography: [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1]]", r": 'homography' must be 3 rows of 3 numbers"),
        ("homography: [[1, 0], [0, 1]]", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: [1, 0, 0, 0, 1, 0, 0, 0]", r": homography: expected 9 numbers .*got 8"),
        ("homography: [1, 0, 0, 0, 1, 0, 0, 0, 1, 0]", r": homography: expected 9 numbers .*got 10"),
        ("homography: []", r": homography: expected 9 numbers .*got 0"),
        ("homography: ['1', '0', '0', '0', '1', '0', '0', '0', '1']", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: [[a, b, c], [d, e, f], [g, h, i]]", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: [true, 0, 0, 0, 1, 0, 0, 0, 1]", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: [null, 0, 0, 0, 1, 0, 0, 0, 1]", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: identity", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: 7", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: {a: 1}", r": 'homography' must be a 3x3 list of numbers"),
        ("homography: [.nan, 0, 0, 0, 1, 0, 0, 0, 1]", r": homography: contains NaN or infinite"),
        ("homography: [.inf, 0, 0, 0, 1, 0, 0, 0, 1]", r": homography: contains NaN or infinite"),
        ("homography: [0, 0, 0, 0, 0, 0, 0, 0, 0]", r": homography: all zeros"),
        ("homography: [[1, 2, 3], [2, 4, 6], [0, 0, 1]]", r": homography: singular"),
    ],
)
def test_bad_contents_name_the_file_and_what_is_wrong(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "cam.yaml"
    path.write_text(text)
    with pytest.raises(InvalidArgument, match=in_file(path) + message):
        load_homography(path)


def test_integer_too_large_for_a_float(tmp_path: Path) -> None:
    # A YAML integer with 401 digits: a number, but not one a float64 can hold.
    path = tmp_path / "cam.yaml"
    path.write_text(f"homography: [{10**400}, 0, 0, 0, 1, 0, 0, 0, 1]\n")
    with pytest.raises(InvalidArgument, match=in_file(path)):
        load_homography(path)


def test_binary_file(tmp_path: Path) -> None:
    # Not UTF-8 text at all (e.g. the video file given by mistake).
    path = tmp_path / "cam.avi"
    path.write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x81\xfe")
    with pytest.raises(InvalidArgument, match=in_file(path)):
        load_homography(path)


def test_loaded_homography_is_a_validated_homography(tmp_path: Path) -> None:
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({"homography": [[2, 0, 0], [0, 2, 0], [0, 0, 2]]}))
    h = load_homography(path)
    assert isinstance(h, Homography)
    assert np.array_equal(h.matrix, np.eye(3))
