"""The object-type grammar (drvs.core.object_types) is the core's: validating a request parses every
filter_def syntax without loading OpenCV or a detector plug-in, on a robot and on the server, with
real interpreters; the typed builders (drvs.hsv, drvs.aruco, ...) produce strings the grammar
accepts and refuse bad arguments by name; a third-party plug-in still adds its own prefix."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import drvs
from drvs.core import object_types
from drvs.core.errors import InvalidArgument
from drvs.core.object_types import HsvRange, MarkerType, ModelType, object_type
from tests.core.test_object_types import plugin_env

ROOT = Path(__file__).resolve().parents[2]
ONE_OF_EACH: tuple[str, ...] = ("hsv_014110130035225200", "hsv_170100100010255255", "aruco_4x4_50")
ONE_OF_EACH += ("aruco_original_7", "people", "foreground", "model_yolo", "model_yolo_traffic_light")
#: After the code ran: OpenCV and drvs.detectors (any of its modules) must not have been loaded.
NOTHING_HEAVY = (
    "heavy = sorted(m for m in sys.modules if m == 'cv2' or m.startswith(('cv2.', 'drvs.detectors')))\n"
    "assert not heavy, heavy\n"
)


def run_python(code: str, env: dict[str, str] | None = None) -> str:
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT, env=env)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_a_robot_validates_every_kind_of_request_without_opencv_or_a_detector() -> None:
    code = (
        "import sys\n"
        "from shapely.geometry import box\n"
        "from drvs.core.model import DetectionRequest\n"
        f"for f in {ONE_OF_EACH!r}:\n"
        "    r = DetectionRequest('r1', 'bot', f, box(0, 0, 1, 1), '127.0.0.1:5000')\n"
        "    r.validate()\n"
        "    r.validate(unknown_types=True)\n"
        "    print(r.kind)\n"
        "r = DetectionRequest('r1', 'bot', 'stripes_3', box(0, 0, 1, 1), '127.0.0.1:5000')\n"
        "r.validate(unknown_types=True)  # left to the server\n" + NOTHING_HEAVY
    )
    kinds = run_python(code).split()
    assert kinds == ["hsv", "hsv", "aruco", "aruco", "people", "foreground", "model_yolo", "model_yolo"]


def test_the_server_parses_robots_requests_without_opencv_or_a_detector() -> None:
    """drvs.wire.convert.request_from_pb is what the server validates a robot's request with."""
    code = (
        "import sys\n"
        "from shapely.geometry import box\n"
        "from drvs.wire.convert import request_from_pb, request_to_pb\n"
        "from drvs.core.errors import InvalidArgument\n"
        "from drvs.core.model import DetectionRequest\n"
        "def pb(f):\n"
        "    return request_to_pb(DetectionRequest('r1', 'bot', f, box(0, 0, 1, 1), '127.0.0.1:5000'))\n"
        f"for f in {ONE_OF_EACH!r}:\n"
        "    print(request_from_pb(pb(f)).kind)\n"
        "for bad in ('hsv_1', 'aruco_9x9_50', 'people_2', 'model_Yolo', 'purple_1'):\n"
        "    try:\n"
        "        request_from_pb(pb(bad))\n"
        "    except InvalidArgument as exc:\n"
        "        assert str(exc).startswith('filter_def: '), exc\n"
        "    else:\n"
        "        raise AssertionError(bad)\n" + NOTHING_HEAVY
    )
    assert run_python(code).split()[-1] == "model_yolo"


def test_a_plug_in_installed_beside_the_server_adds_its_grammar(tmp_path: Path) -> None:
    """A prefix nobody registered loads the installed plug-ins once: the plug-in's own parser then
    answers (and its errors), and the built-in types still never needed it."""
    code = (
        "import sys\n"
        "from drvs.core.errors import InvalidArgument\n"
        "from drvs.core.object_types import detector_kind, is_known_type\n"
        "assert detector_kind('people') == 'people' and not is_known_type('yellowish_30')\n" + NOTHING_HEAVY + ""
        "assert detector_kind('yellowish_30') == 'yellowish' and is_known_type('greenish_1')\n"
        "try:\n"
        "    detector_kind('yellowish_x')\n"
        "except InvalidArgument as exc:\n"
        "    print(exc)\n"
    )
    out = run_python(code, env=plugin_env(tmp_path))
    assert "'yellowish_x' is not 'yellowish_' and a minimum area in pixels" in out


def test_the_grammar_parses_typed_parameters() -> None:
    assert object_type("hsv_170100100010255255").params == HsvRange(170, 100, 100, 10, 255, 255)
    assert object_type("hsv_170100100010255255").params.wraps
    aruco = object_type("aruco_apriltag_36h11_586")
    assert (aruco.kind, aruco.key, aruco.params) == ("aruco", "aruco_apriltag_36h11", MarkerType("apriltag_36h11", 586))
    model = object_type("model_yolo_traffic_light")
    assert (model.kind, model.key, model.params) == ("model_yolo", "model_yolo", ModelType("yolo", "traffic_light"))
    assert object_type("model_yolo").params == ModelType("yolo", None)
    assert object_type("people").params is None and object_type("foreground").kind == "foreground"


def test_the_builders_write_what_the_grammar_accepts() -> None:
    cases = {
        drvs.hsv((14, 110, 130), (35, 225, 200)): "hsv_014110130035225200",
        drvs.hsv((170, 100, 100), (10, 255, 255)): "hsv_170100100010255255",  # red wraps through 0
        drvs.hsv([0, 0, 0], [179, 255, 255]): "hsv_000000000179255255",
        drvs.aruco("4x4_50"): "aruco_4x4_50",
        drvs.aruco("apriltag_36h11", 586): "aruco_apriltag_36h11_586",
        drvs.people(): "people",
        drvs.foreground(): "foreground",
        drvs.model_type("yolo"): "model_yolo",
        drvs.model_type("yolo-v8", "traffic_light"): "model_yolo-v8_traffic_light",
    }
    for built, expected in cases.items():
        assert built == expected
        object_type(built)
    assert object_types.model is drvs.model_type


@pytest.mark.parametrize(
    ("build", "args", "message"),
    [
        (drvs.hsv, ((180, 0, 0), (10, 255, 255)), r"hsv: lo H = 180 is out of range 0-179"),
        (drvs.hsv, ((0, 0, 0), (10, 256, 255)), r"hsv: hi S = 256 is out of range 0-255"),
        (drvs.hsv, ((0, 0, -1), (10, 255, 255)), r"hsv: lo V = -1 is out of range 0-255"),
        (drvs.hsv, ((0, 200, 0), (10, 100, 255)), r"hsv: lo S = 200 > hi S = 100 \(only H wraps\)"),
        (drvs.hsv, ((0, 0, 0, 0), (10, 100, 255)), r"hsv: lo = \(0, 0, 0, 0\) is not an \(H, S, V\) triple"),
        (drvs.hsv, ("red", (10, 100, 255)), r"hsv: lo = 'red' is not an \(H, S, V\) triple"),
        (drvs.hsv, ((0, 0, 0), (10.5, 100, 255)), r"hsv: hi H = 10.5 is not an integer"),
        (drvs.aruco, ("4X4_50",), r"aruco: dictionary '4X4_50' is not one of 4x4_50, "),
        (drvs.aruco, ("4x4_50", 50), r"aruco: marker_id 50 is not an integer in 0-49"),
        (drvs.aruco, ("4x4_50", True), r"aruco: marker_id True is not an integer"),
        (drvs.model_type, ("yolo_v8",), r"model: name 'yolo_v8' must be 1-24 lower-case letters"),
        (drvs.model_type, ("yolo", "traffic light"), r"model: cls 'traffic light' must be 1-32 letters"),
        (drvs.model_type, ("yolo", ""), r"model: cls '' must be"),
    ],
)
def test_the_builders_refuse_bad_arguments_by_name(build: Any, args: tuple[Any, ...], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        build(*args)


def test_import_drvs_and_its_builders_load_neither_opencv_nor_grpc() -> None:
    code = (
        "import sys, drvs\n"
        "drvs.hsv((1, 2, 3), (4, 5, 6)); drvs.aruco('4x4_50', 1); drvs.model_type('yolo')\n"
        "assert 'cv2' not in sys.modules and 'grpc' not in sys.modules, sorted(sys.modules)\n" + NOTHING_HEAVY
    )
    run_python(code)
