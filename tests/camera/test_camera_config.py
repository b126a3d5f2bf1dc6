"""The camera node's config (flag > env > file > default), and its health following its frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc

from drvs.camera.config import DEFAULT_SERVER, load_config
from drvs.core.errors import InvalidArgument
from drvs.robot import DrvsClient
from drvs.tools.launch import ManagedProcess, camera_ready
from tests.helpers import CAM1_REGION, YELLOW, Office

NO_FLAGS: dict[str, object] = {}


def write(path: Path, data: dict[str, object]) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def test_precedence_flag_env_file_default(tmp_path: Path) -> None:
    cfg = write(tmp_path / "cam.yaml", {"id": "from-file", "source": "0", "homography": "h.yaml", "max_range_m": 7})
    c = load_config(NO_FLAGS, {}, cfg)
    assert (c.id, c.max_range_m, c.server) == ("from-file", 7.0, DEFAULT_SERVER)
    assert c.homography == tmp_path / "h.yaml"  # relative to the config file
    c = load_config(NO_FLAGS, {"DRVS_CAMERA_ID": "from-env", "DRVS_CAMERA_MAX_RANGE": "9"}, cfg)
    assert (c.id, c.max_range_m) == ("from-env", 9.0)
    c = load_config({"id": "from-flag", "max_range_m": 3.0}, {"DRVS_CAMERA_ID": "from-env"}, cfg)
    assert (c.id, c.max_range_m) == ("from-flag", 3.0)
    c = load_config({"loop": False}, {"DRVS_CAMERA_SERVE_FRAMES": "yes"}, cfg)
    assert c.loop is False and c.serve_frames is True


@pytest.mark.parametrize(
    ("data", "environ", "message"),
    [
        ({"id": "a", "source": "0", "homography": "h", "max_rang_m": 3}, {}, r"max_rang_m: unknown key"),
        ({"source": "0", "homography": "h"}, {}, r"id: missing; give --id, DRVS_CAMERA_ID or id: in a --config file"),
        ({"id": "a", "source": "0", "homography": "h", "max_range_m": -1}, {}, r"max_range_m \(from config .*\): -1"),
        (
            {"id": "a", "source": "0", "homography": "h"},
            {"DRVS_CAMERA_MIN_AREA": "big"},
            r"min_area_px \(from DRVS_CAMERA_MIN_AREA\)",
        ),
        ({"id": "a b", "source": "0", "homography": "h"}, {}, r"id \(from config .*\): 'a b' may hold only"),
        ({"id": "a", "source": "0", "homography": "h", "server": "nowhere"}, {}, r"server \(from config .*\)"),
        (
            {"id": "a", "source": "0", "homography": "h", "loop": "maybe"},
            {},
            r"loop \(from config .*\): 'maybe' is not true or false",
        ),
    ],
)
def test_bad_config_names_the_key_and_its_origin(
    tmp_path: Path, data: dict[str, object], environ: dict[str, str], message: str
) -> None:
    with pytest.raises(InvalidArgument, match=message):
        load_config(NO_FLAGS, environ, write(tmp_path / "cam.yaml", data))


@pytest.mark.office_cameras()
async def test_node_runs_from_a_config_file(tmp_path: Path, office: Office) -> None:
    rec = office.recorded["cam1"]
    cfg = write(
        tmp_path / "cam.yaml",
        {"id": "cfgcam", "source": str(rec.video), "homography": str(rec.homography_file),
         "server": office.address, "max_range_m": 6},
    )  # fmt: skip
    proc = await ManagedProcess.entry_point("cfgcam", "drvs-camera", "--config", str(cfg)).start()
    try:
        await camera_ready(proc, "cfgcam")
        async with DrvsClient(office.address) as robot:
            assert "cfgcam" in [c.camera_id for c in await robot.cameras()]
    finally:
        assert await proc.stop() == 0


async def health(address: str) -> int:
    async with aio.insecure_channel(address) as channel:
        reply = await health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""), timeout=5)
        return int(reply.status)


@pytest.mark.slow
@pytest.mark.office_cameras()
@pytest.mark.timeout(200)  # its own waits (starts, runs, requests) add up to 170 s
async def test_source_that_disappears_and_comes_back(tmp_path: Path, office: Office) -> None:
    rec = office.recorded["cam1"]
    video = tmp_path / "live.avi"
    shutil.copy(rec.video, video)
    proc = ManagedProcess.entry_point(
        "flaky", "drvs-camera", "--id", "flaky", "--source", str(video), "--homography", str(rec.homography_file),
        "--server", office.address, "--max-range", "6", "--max-frame-age", "0.5",
    )  # fmt: skip
    await proc.start()
    try:
        address = await camera_ready(proc, "flaky")
        assert await health(address) == health_pb2.HealthCheckResponse.SERVING

        video.unlink()  # the camera goes away: the file ends and cannot be reopened
        await proc.wait_for_line(r"NOT_SERVING until frames come back", timeout=15)
        assert await health(address) == health_pb2.HealthCheckResponse.NOT_SERVING
        async with DrvsClient(office.address) as robot:
            result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
            flaky = [r for r in result.reports if r.camera_id == "flaky"]
            assert flaky and "no fresh frame" in flaky[0].error  # it says so rather than guess

            shutil.copy(rec.video, video)  # and comes back
            await proc.wait_for_line(r"frames again from .*; SERVING", timeout=15)
            assert await health(address) == health_pb2.HealthCheckResponse.SERVING
            result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
            flaky = [r for r in result.reports if r.camera_id == "flaky"]
            assert flaky and not flaky[0].error and len(flaky[0].detections) == 2
        # It stayed registered throughout: no flapping in and out of routing.
        assert "re-registered" not in proc.output()
        assert "flaky left routing" not in office.server.output()
    finally:
        assert await proc.stop() == 0


def test_capture_detector_and_heartbeat_settings(tmp_path: Path) -> None:
    cfg = write(
        tmp_path / "cam.yaml",
        {"id": "a", "source": "0", "homography": "h", "resolution": [1280, 720], "fps": 15, "detectors": ["hsv"],
         "heartbeat_s": 2},
    )  # fmt: skip
    c = load_config(NO_FLAGS, {}, cfg)
    assert (c.resolution, c.fps, c.detectors, c.heartbeat_s) == ((1280, 720), 15.0, ("hsv",), 2.0)
    c = load_config({"resolution": "640x480"}, {"DRVS_CAMERA_DETECTORS": "hsv"}, cfg)
    assert c.resolution == (640, 480) and c.detectors == ("hsv",)
    with pytest.raises(InvalidArgument, match=r"detectors \(from config .*\): 'yolo' is not an installed detector"):
        load_config(
            NO_FLAGS,
            {},
            write(tmp_path / "b.yaml", {"id": "a", "source": "0", "homography": "h", "detectors": ["yolo"]}),
        )
    with pytest.raises(InvalidArgument, match=r"resolution \(from --resolution\): 1x1 is not a camera resolution"):
        load_config({"resolution": "1,1"}, {}, cfg)
    # Detector settings reach the detectors: a flag, the environment, the file, in that order.
    people = load_config({"people_min_height_px": "85"}, {"DRVS_CAMERA_DETECT_WORKERS": "3"}, cfg)
    assert people.detector_options() == {"people": {"min_height_px": 85.0}} and people.detect_workers == 3
    both = load_config({"people_height_m": "1.6"}, {"DRVS_CAMERA_PEOPLE_MIN_HEIGHT": "90"}, cfg)
    assert both.detector_options() == {"people": {"min_height_px": 90.0, "person_height_m": 1.6}}
    assert load_config(NO_FLAGS, {}, cfg).detector_options() == {}


def test_heartbeat_never_outlives_the_lease(tmp_path: Path) -> None:
    from drvs.camera.node import CameraNode
    from drvs.camera.source import VideoSource
    from drvs.core.geometry import homography_from_pose

    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))
    node = CameraNode("a", VideoSource("0"), h, "127.0.0.1:1", heartbeat_s=2.0)
    assert node.registration.heartbeat_interval(10.0) == 2.0
    assert node.registration.heartbeat_interval(3.0) == 1.5  # at most half the lease
    assert CameraNode("b", VideoSource("0"), h, "127.0.0.1:1").registration.heartbeat_interval(9.0) == 3.0


@pytest.mark.parametrize(
    ("wrong", "message"),
    [
        ({"server": 50051}, r"^server: expected a string such as 'host:50051', got int$"),
        ({"source": "0"}, r"^source: expected a frame source \(VideoSource, PushSource, any FrameSource\), got str$"),
        ({"homography": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, r"^homography: expected a Homography .*, got list$"),
        ({"resolution": (640, 0)}, r"^resolution: \(640, 0\) is not \(width, height\) in whole pixels above 0$"),
        ({"resolution": "640x480"}, r"^resolution: '640x480' is not"),
        ({"detector_options": {"poeple": {}}}, r"^detector_options: \['poeple'\]: no such detector"),
        ({"detector_options": {"people": 1.8}}, r"^detector_options: expected \{prefix: \{option: value\}\}"),
    ],
)  # fmt: skip
def test_camera_node_refuses_wrong_arguments_naming_them(wrong: dict[str, object], message: str) -> None:
    """CameraNode(...) from Python: an argument of the wrong kind is refused where it is made,
    naming it, where it was an AttributeError at start(), a failure after the first frame, or
    (a detector's options under a misspelt name) silently ignored."""
    from drvs.camera.node import CameraNode
    from drvs.camera.source import PushSource
    from drvs.core.geometry import homography_from_pose

    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))
    arguments: dict[str, object] = {"camera_id": "a", "source": PushSource(), "homography": h, "server": "127.0.0.1:1"}
    with pytest.raises(InvalidArgument, match=message):
        CameraNode(**{**arguments, **wrong})  # type: ignore[arg-type]
    CameraNode(**arguments)  # type: ignore[arg-type]


@pytest.mark.office_cameras()
async def test_a_source_of_another_size_is_refused(office: Office) -> None:
    rec = office.recorded["cam1"]
    proc = ManagedProcess.entry_point(
        "small", "drvs-camera", "--id", "small", "--source", str(rec.video), "--homography", str(rec.homography_file),
        "--server", office.address, "--resolution", "320,240",
    )  # fmt: skip
    await proc.start()
    # Found only at start: exit 1 (docs/validation.md), a log line, no traceback.
    assert await proc.wait(timeout=30) == 1 and "Traceback" not in proc.output(), proc.output()
    assert "the source gives 640x480, not the configured 320x240" in proc.output()
