"""Builders and constants the tests share. conftest.py holds fixtures only; a test module imports
what it needs from here, never from another test module."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import math
import os
import re
import shutil
import time
import urllib.request
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from numpy.typing import NDArray

from drvs.core.filters import HsvRange
from drvs.core.geometry import FieldOfView, Homography, homography_from_pose
from drvs.core.mobile import Mount
from drvs.core.model import Pose2
from drvs.detectors import DEFAULT_MIN_AREA_PX, CameraView, HsvDetector
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import CameraDef, Scenario
from drvs.sim.scene import FloorPatch, RecordedCamera, record_camera, render_view
from drvs.tools.fakes import AckingCamera
from drvs.tools.fakes import register_message as register_message  # re-exported for the tests
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from drvs.wire import _grpc

# --- the recorded two-camera floor (the `recorded` and `office` fixtures) -----------------------

YELLOW = "hsv_014110130035225200"
GREEN = "hsv_040080080080255255"
RED = "hsv_170100100010255255"
BLUE = "hsv_100150100130255255"
IMAGE_SIZE = (640, 480)
#: Fields of view: cam1 sees about x -3.8..3.8, y 1.5..7.5; cam2 the same 20 m further along x.
CAMERA_POSES = {"cam1": (0.0, 0.0, 3.0), "cam2": (20.0, 0.0, 3.0)}
CAM1_REGION = (-6.0, 0.0, 6.0, 10.0)
#: Inside cam1's field of view, around cam1's two yellow discs: a region seen whole (nothing uncovered).
CAM1_SEEN = (-1.5, 2.2, 2.0, 5.0)
CAM2_REGION = (14.0, 0.0, 26.0, 10.0)
BOTH_REGION = (-6.0, 0.0, 26.0, 10.0)
MAX_RANGE = "6"


@dataclass(frozen=True)
class TrueObject:
    filter_def: str
    center: tuple[float, float]
    radius: float


OBJECTS = [
    TrueObject(YELLOW, (-1.0, 4.0), 0.25),
    TrueObject(YELLOW, (1.5, 3.0), 0.20),
    TrueObject(GREEN, (0.0, 5.5), 0.30),
    TrueObject(YELLOW, (19.0, 4.5), 0.30),
    TrueObject(YELLOW, (21.5, 6.0), 0.25),
]


def nearest(filter_def: str, x: float, y: float) -> tuple[TrueObject, float]:
    obj = min((o for o in OBJECTS if o.filter_def == filter_def), key=lambda o: math.dist(o.center, (x, y)))
    return obj, math.dist(obj.center, (x, y))


def record_floor(directory: Path) -> dict[str, RecordedCamera]:
    """Two cameras' video files of the same floor (OBJECTS), with their homography files."""
    patches = [FloorPatch.disc(o.center, o.radius, HsvRange.parse(o.filter_def).centre_bgr()) for o in OBJECTS]
    out = {}
    for seed, (camera_id, position) in enumerate(CAMERA_POSES.items()):
        h = homography_from_pose(position, 90.0, 40.0, 60.0, IMAGE_SIZE)
        out[camera_id] = record_camera(directory, camera_id, h, IMAGE_SIZE, patches, seed=seed)
    return out


@dataclass
class Office:
    """A drvs-server process and the camera processes started on it (none, one or both of `recorded`)."""

    server: ManagedProcess
    address: str
    cameras: dict[str, ManagedProcess]
    recorded: dict[str, RecordedCamera]

    async def start_camera(self, camera_id: str) -> ManagedProcess:
        rec = self.recorded[camera_id]
        # DEBUG: the tests read which requests each camera received from its log.
        proc = await start_camera(
            camera_id, rec.video, rec.homography_file, self.address, "--max-range", MAX_RANGE, "--log-level", "DEBUG"
        )
        self.cameras[camera_id] = proc
        return proc


async def start_office(
    recorded: dict[str, RecordedCamera], lease_ttl: float, cameras: tuple[str, ...] | None = None
) -> Office:
    """The server, then the cameras named (default: every recorded one). All stopped if one fails."""
    server, address = await start_server("--lease-ttl", str(lease_ttl))
    office = Office(server, address, {}, recorded)
    try:
        for camera_id in recorded if cameras is None else cameras:
            await office.start_camera(camera_id)
    except BaseException:
        await asyncio.shield(stop_office(office))
        raise
    return office


async def stop_office(office: Office) -> None:
    """Stops (and reaps) every process, even when one of them fails to stop cleanly."""
    try:
        for proc in office.cameras.values():
            await proc.stop()
    finally:
        await office.server.stop()


# --- command lines -----------------------------------------------------------------------------


def roi(region: tuple[float, float, float, float]) -> str:
    return ",".join(str(v) for v in region)


async def run_robot(*args: str) -> tuple[int, list[str]]:
    """drvs-robot with `args`: (exit code, output lines). Killed and reaped if it runs over 30 s."""
    proc = await ManagedProcess.entry_point("robot", "drvs-robot", *args).start()
    code = await proc.wait(timeout=30)
    return code, proc.lines


# --- raw protobuf messages ---------------------------------------------------------------------


def detect_message(**overrides: object) -> detection_pb2.DetectionRequest:
    msg = detection_pb2.DetectionRequest(
        request_id="req-1",
        robot_id="r",
        filter_def=YELLOW,
        region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=-1, y_lower=0, x_upper=1, y_upper=5)),
        callback_address="127.0.0.1:9",
    )
    for key, value in overrides.items():
        if value is None:
            msg.ClearField(key)
        elif isinstance(value, str):
            setattr(msg, key, value)
        else:
            getattr(msg, key).CopyFrom(value)
    return msg


# --- metrics -----------------------------------------------------------------------------------


def metrics_port(proc: ManagedProcess) -> int:
    for line in proc.lines:
        m = re.search(r"metrics on http://[^:]+:(\d+)/metrics", line)
        if m:
            return int(m.group(1))
    raise AssertionError(f"{proc.name} did not say where its metrics are:\n{proc.output()}")


async def scrape(port: int) -> dict[str, float]:
    def get() -> str:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as response:
            return str(response.read().decode())

    text = await asyncio.to_thread(get)
    values: dict[str, float] = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            values[name] = float(value)
    return values


T = TypeVar("T")


async def poll(
    read: Callable[[], Awaitable[T]],
    until: Callable[[T], object] = bool,
    *,
    what: str,
    timeout: float = 10.0,
    every: float = 0.05,
) -> T:
    """`await read()` every `every` s until `until` holds for what it returns, and return that: for
    another process's state (a server's routing, its metrics), which tells no one when it changes.
    Fails after `timeout` s, saying `what` was awaited and what was read last."""
    deadline = time.monotonic() + timeout
    while not until(value := await read()):
        assert time.monotonic() < deadline, f"still not {what} after {timeout} s (last read: {value!r})"
        await asyncio.sleep(every)
    return value


async def metrics_at_least(port: int, name: str, value: float, timeout: float = 10.0) -> dict[str, float]:
    """The metrics on `port` once `name` has reached `value` (polled: another process's counter)."""
    return await poll(
        lambda: scrape(port), lambda values: values.get(name, 0.0) >= value, what=f"{name} >= {value}", timeout=timeout
    )


async def wait_until(check: Callable[[], object], what: str = "the condition", timeout: float = 5.0) -> None:
    """Poll `check()` (a state the test cannot be told about) until true; fail after `timeout` s."""

    async def read() -> object:
        return check()

    await poll(read, what=what, timeout=timeout, every=0.01)


# --- real footage ------------------------------------------------------------------------------

VTEST = Path("/usr/share/doc/opencv-doc/examples/data/vtest.avi")


def footage() -> Path:
    """OpenCV's vtest.avi (Debian's opencv-doc): a failure where ./run test could have installed it, a
    skip only where it cannot (no root or no apt-get)."""
    if VTEST.is_file():
        return VTEST
    if os.geteuid() == 0 and shutil.which("apt-get"):
        pytest.fail(f"{VTEST} is missing on a machine that can install it: ./run test installs opencv-doc")
    pytest.skip(f"{VTEST} is absent and only root with apt-get can install it (apt-get install opencv-doc)")


# --- discs rendered by one reference camera (colour detection) ---------------------------------


@dataclass(frozen=True)
class Disc:
    filter_def: str
    center: tuple[float, float]
    radius: float

    @property
    def area(self) -> float:
        return math.pi * self.radius**2

    def patch(self) -> FloorPatch:
        return FloorPatch.disc(self.center, self.radius, HsvRange.parse(self.filter_def).centre_bgr())


#: All lie well inside the reference camera's view (x -1.8..1.8 at y 1.5, x -5.6..5.6 at y 10.1).
BIG = [
    Disc(YELLOW, (-1.0, 4.0), 0.25),
    Disc(YELLOW, (1.5, 3.0), 0.20),
    Disc(GREEN, (0.0, 5.5), 0.30),
    Disc(RED, (-2.0, 7.0), 0.30),
]


def camera() -> Homography:
    """The reference camera: 3 m up at the origin, looking 40 degrees down along +y."""
    return homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, IMAGE_SIZE)


def detector(h: Homography, max_range_m: float = 15.0, min_area_px: float = DEFAULT_MIN_AREA_PX) -> HsvDetector:
    fov = FieldOfView.compute(h, IMAGE_SIZE, max_range_m)
    return HsvDetector(CameraView(h, fov, IMAGE_SIZE, camera_id="cam1", min_area_px=min_area_px))


def render(discs: list[Disc], noise_sigma: float = 0.0) -> NDArray[np.uint8]:
    return render_view(
        camera(), IMAGE_SIZE, [d.patch() for d in discs], noise_sigma=noise_sigma, rng=np.random.default_rng(3)
    )


def serving_detection(servicer: detection_pb2_grpc.DetectObjectBoundaryServicer) -> AbstractAsyncContextManager[str]:
    """A real gRPC server in this process serving `servicer` as DetectObjectBoundary (a camera or
    a server stand-in) on a free loopback port; yields its address, stops it on leaving."""
    return serving(servicer, detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server)


@contextlib.asynccontextmanager
async def serving(servicer: Any, add: Callable[[Any, Any], None]) -> AsyncIterator[str]:
    """A real gRPC server in this process serving `servicer`, added by its `add_…_to_server`
    function, on a free loopback port; yields its address, stops it on leaving."""
    server = _grpc.new_server()
    add(servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        yield f"127.0.0.1:{port}"
    finally:
        await server.stop(0)


def record_facing(
    directory: Path, poses: dict[str, tuple[float, float, float]], patches: list[FloorPatch]
) -> dict[str, RecordedCamera]:
    """One recorded camera per id at its (x, y, height) position, all looking along +y (yaw 90°,
    pitch 40°, 60° wide, IMAGE_SIZE) at the same floor patches; each with its own noise seed."""
    return {
        camera_id: record_camera(
            directory, camera_id, homography_from_pose(pose, 90.0, 40.0, 60.0, IMAGE_SIZE), IMAGE_SIZE, patches, seed=i
        )
        for i, (camera_id, pose) in enumerate(poses.items())
    }


@dataclass
class Scene:
    """A drvs-server process, its address, and its camera processes by id."""

    server: ManagedProcess
    address: str
    cameras: dict[str, ManagedProcess]


# --- a mobile camera on a rendered floor (tests/camera/test_mobile_camera.py, test_mobile_pickup.py) ----

#: 0.8 m up, 0.1 m ahead of the robot's centre, looking forward 30° down, 70° wide.
MOUNT = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0)
MOBILE_SIZE = (640, 480)
#: The yellow disc of MOBILE_SCENE.
MOBILE_TARGET = (3.0, 2.0)
MOBILE_SCENE = f"""
name: mobile-test
floor_plan:
  bounds: [0, 0, 8, 4]
  walls: []
colors:
  yellow: {{filter_def: {YELLOW}, bgr: [57, 143, 165]}}
  blue:   {{filter_def: hsv_100120080130255255, bgr: [167, 100, 42]}}
cameras:
  - {{id: unused, position: [4.0, -2.0, 4.5], yaw_deg: 90, pitch_deg: 50, hfov_deg: 90,
     resolution: [640, 480], fps: 20}}
objects:
  - {{kind: marker, color: yellow, center: [{MOBILE_TARGET[0]}, {MOBILE_TARGET[1]}], radius: 0.15}}
robot: {{start: [0.5, 0.5], goal: [7.0, 0.5], radius: 0.2, color: blue, speed_mps: 1.0}}
mission: navigate
"""


def mounted_camera(pose: Pose2, camera_id: str = "scout-cam") -> CameraDef:
    """The simulator's camera where MOUNT on a robot at `pose` puts it."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    position = (pose.x + c * MOUNT.x - s * MOUNT.y, pose.y + s * MOUNT.x + c * MOUNT.y, MOUNT.z)
    yaw = math.degrees(pose.yaw) + MOUNT.yaw_deg
    return CameraDef(camera_id, position, yaw, MOUNT.pitch_deg, MOUNT.hfov_deg, MOBILE_SIZE, 20.0, 6.0)


def mounted_frame(scenario: Scenario, pose: Pose2, version: int = 0) -> NDArray[np.uint8]:
    """What the camera on MOUNT of a robot at `pose` sees of `scenario` (MOBILE_SCENE, parsed)."""
    return CameraRenderer(scenario, mounted_camera(pose), seed=3).render(None, version)


class CapturingCamera(AckingCamera):
    """A camera endpoint that accepts every forwarded request and keeps it (in `requests`): it
    learns what a camera learns, and reports nothing unless the test writes it."""

    def __init__(self) -> None:
        super().__init__()
        self.requests: asyncio.Queue[detection_pb2.DetectionRequest] = asyncio.Queue()

    async def batch(self, requests: Sequence[detection_pb2.DetectionRequest]) -> None:
        for message in requests:
            self.requests.put_nowait(message)


CV2_WITHOUT = Path(__file__).parent / "data" / "cv2_without"


def without(*names: str) -> dict[str, str]:
    """An environment whose Python's cv2 lacks `names` (see tests/data/cv2_without)."""
    path = os.pathsep.join([str(CV2_WITHOUT), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path, "DRVS_TEST_CV2_WITHOUT": ",".join(names)}


async def once_per_run(
    tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], Awaitable[dict[str, Any]]]
) -> dict[str, Any]:
    """`make(folder)` once for the whole test run, for the tests that read the same run of something
    (each checking its own part of it), also across pytest-xdist's workers: under xdist the first
    worker to ask makes it in a folder every worker shares, holding a lock there; another that asks
    meanwhile waits on the lock, then reads what the first left (`make`'s JSON). If `make` fails,
    the next to ask makes it anew. Without xdist: `make` in a new folder (callers cache it in a fixture)."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return await make(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent  # this run's, above every worker's own
    done = shared / f"{name}.json"
    with (shared / f"{name}.lock").open("w") as lock:
        await asyncio.to_thread(fcntl.flock, lock, fcntl.LOCK_EX)
        try:
            if done.exists():
                return dict(json.loads(done.read_text()))
            folder = shared / name
            shutil.rmtree(folder, ignore_errors=True)  # a failed try's leftovers
            folder.mkdir()
            value = await make(folder)
            done.write_text(json.dumps(value))
            return value
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
