"""docs/validation.md against the real thing: every row marked ✓ there is sent here to a real server
(on a real socket) or given to a real drvs-server / drvs-camera process, and must get the status
and message the table says. The patterns are read from the document, so the two cannot drift."""

from __future__ import annotations

import asyncio
import math
import os
import re
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import pytest
import pytest_asyncio
from grpc import aio

from drvs.core.geometry import homography_from_pose
from drvs.core.mobile import Mount
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.tools.launch import ManagedProcess
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2, registry_pb2, registry_pb2_grpc
from tests.helpers import detect_message

DOC = Path(__file__).resolve().parents[2] / "docs" / "validation.md"
YELLOW = "hsv_014110130035225200"
GOOD_H = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480)).to_list()
#: In the document's messages these stand for whatever varies.
WILDCARDS = re.compile(r"(…|FILE|KEY)")


def table_rows() -> list[list[str]]:
    """The body rows of every table (not the headers), as lists of cells."""
    lines = DOC.read_text().splitlines()
    separator = re.compile(r"^\|[-| ]+\|$")
    rows = []
    for i, line in enumerate(lines):
        header = i + 1 < len(lines) and separator.match(lines[i + 1])
        if line.startswith("|") and not separator.match(line) and not header:
            rows.append([cell.strip() for cell in line.strip("|").split(" | ")])
    return rows


def quoted(cell: str) -> list[str]:
    return re.findall(r"`([^`]+)`", cell)


def documented(pattern: str, status: str | None = None) -> re.Pattern[str]:
    """The row giving `pattern` (and `status`, for gRPC rows) must exist; returns it as a regex."""
    rows = [r for r in table_rows() if any(pattern in quoted(c) for c in r) and (status is None or status in r)]
    assert rows, f"docs/validation.md has no row with `{pattern}`" + (f" and {status}" if status else "")
    parts = WILDCARDS.split(pattern)
    return re.compile("".join(".*" if WILDCARDS.fullmatch(p) else re.escape(p) for p in parts), re.S)


def box(x0: float, y0: float, x1: float, y1: float) -> geometry_pb2.Region:
    return geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1))


def polygon(*points: tuple[float, float]) -> geometry_pb2.Region:
    return geometry_pb2.Region(polygon=geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=x, y=y) for x, y in points]))


def request(**overrides: Any) -> detection_pb2.DetectionRequest:
    return detect_message(**overrides)


def continuous(rate: float, duration: float) -> detection_pb2.ContinuousMode:
    return detection_pb2.ContinuousMode(rate_hz=rate, duration_s=duration)


def registration(**overrides: Any) -> registry_pb2.RegisterRequest:
    msg = registry_pb2.RegisterRequest(
        camera_id="cam1", address="127.0.0.1:9", homography=registry_pb2.Homography(m=GOOD_H),
        image_width=640, image_height=480, max_range_m=6.0, detector_kinds=["hsv"],
    )  # fmt: skip
    for key, value in overrides.items():
        if key == "m":
            msg.homography.CopyFrom(registry_pb2.Homography(m=value))
        elif value is None:
            msg.ClearField(key)
        else:
            setattr(msg, key, value)
    return msg


@dataclass(frozen=True)
class Case:
    status: str
    pattern: str
    call: Callable[[Any], Any]  # given the channel, returns an awaitable call


def detect(**overrides: Any) -> Callable[[Any], Any]:
    return lambda ch: detection_pb2_grpc.DetectObjectBoundaryStub(ch).DetectObjects(request(**overrides))


def reporting_to_server() -> detection_pb2.DetectionRequest:
    """A robot's request that sets what only the server sets on its forwards."""
    message = request()
    message.report_to_server = True
    return message


def register(**overrides: Any) -> Callable[[Any], Any]:
    return lambda ch: registry_pb2_grpc.RegisterVisionServiceStub(ch).Register(registration(**overrides))


BOWTIE = polygon((0, 0), (1, 1), (1, 0), (0, 1))
CIRCLE_1001 = [(math.cos(2 * math.pi * i / 1001), math.sin(2 * math.pi * i / 1001)) for i in range(1001)]
#: A valid box carrying 30 000 bytes of an unknown field (number 1023, length-delimited).
PADDED_BOX = geometry_pb2.Region.FromString(
    box(0, 0, 1, 1).SerializeToString() + b"\xfa\x3f" + bytes([0xB0, 0xEA, 0x01]) + b"x" * 30_000
)
PITCHED_UP = homography_from_pose((0, 0, 3), 90, -30, 60, (640, 480)).to_list()
INVALID, DENIED, NOT_FOUND = "INVALID_ARGUMENT", "PERMISSION_DENIED", "NOT_FOUND"

GRPC_CASES = [
    Case(INVALID, "request_id: longer than 128 characters", detect(request_id="a" * 129)),
    Case(INVALID, "robot_id: '…' may hold only letters, digits and - _ . :", detect(robot_id="robot with spaces")),
    Case(INVALID, "filter_def: empty; expected e.g. …", detect(filter_def="")),
    Case(INVALID, "filter_def: unknown object type '…' in '…'; known types: …", detect(filter_def="rgb_0141")),
    Case(
        INVALID,
        "filter_def: '…' is not 'hsv_' followed by 18 digits (six zero-padded 3-digit numbers HloSloVloHhiShiVhi)",
        detect(filter_def="hsv_0141101300352252"),
    ),
    Case(INVALID, "filter_def: H low = 200 is out of range 0-179 in '…'", detect(filter_def="hsv_200110130035225200")),
    Case(INVALID, "filter_def: S low … > S high … in '…'", detect(filter_def="hsv_014210130035100200")),
    Case(
        INVALID,
        "filter_def: '…' names no ArUco dictionary; expected aruco_<dictionary> or aruco_<dictionary>_<id>, "
        "e.g. 'aruco_4x4_50' or 'aruco_4x4_50_7'",
        detect(filter_def="aruco"),
    ),
    Case(
        INVALID,
        "filter_def: unknown ArUco dictionary '…' in '…'; OpenCV's dictionaries are …",
        detect(filter_def="aruco_4X4_50_7"),
    ),
    Case(
        INVALID,
        "filter_def: marker id '…' in '…' is not an integer in 0-… (dictionary … has … markers)",
        detect(filter_def="aruco_apriltag_16h5_30"),
    ),
    Case(
        INVALID,
        "filter_def: '…': the people type takes no parameters; write 'people'",
        detect(filter_def="people_adult"),
    ),
    Case(INVALID, "region: missing; give a box or a polygon", detect(region=None)),
    Case(INVALID, "region.box.x_lower: nan is not finite", detect(region=box(math.nan, 0, 1, 1))),
    Case(INVALID, "region.box.x_upper: 1e+300 is beyond ±1e+06 m", detect(region=box(0, 0, 1e300, 1))),
    Case(INVALID, "region.box: x_lower … must be less than x_upper …", detect(region=box(1, 0, 1, 1))),
    Case(
        INVALID, "region.polygon.points[…].y: inf is not finite", detect(region=polygon((0, 0), (1, math.inf), (0, 1)))
    ),
    Case(INVALID, "region.polygon: needs at least 3 distinct points, got …", detect(region=polygon((0, 0), (1, 1)))),
    Case(INVALID, "region.polygon: not a simple polygon (Self-intersection[…])", detect(region=BOWTIE)),
    Case(INVALID, "region.polygon: … points; at most 1000, simplify the region", detect(region=polygon(*CIRCLE_1001))),
    Case(INVALID, "region: … bytes encoded; at most 24576", detect(region=PADDED_BOX)),
    Case(INVALID, "callback_address: empty; expected host:port", detect(callback_address="")),
    Case(INVALID, "callback_address: '…' is not host:port", detect(callback_address="no port")),
    Case(
        INVALID,
        "callback_address: '…' is not a valid host name or IPv4 address",
        detect(callback_address="bad_host:80"),
    ),
    Case(INVALID, "callback_address: port … is out of range", detect(callback_address="127.0.0.1:0")),
    Case(
        DENIED,
        "callback_address: … is not the requesting robot's address (…); reports go back only to the robot that "
        "asks, or to networks the server allows (--allow-callback)",
        detect(callback_address="10.1.2.3:9"),
    ),
    Case(INVALID, "continuous.rate_hz: nan must be a finite number >= 0", detect(continuous=continuous(math.nan, 1))),
    Case(INVALID, "continuous.rate_hz: … exceeds the limit of 100", detect(continuous=continuous(1000, 1))),
    Case(INVALID, "continuous.duration_s: … exceeds the limit of 3600", detect(continuous=continuous(1, 1e9))),
    Case(
        INVALID,
        "continuous: rate_hz and duration_s must both be > 0 (continuous) or both 0 (single shot); "
        "got rate_hz=…, duration_s=…",
        detect(continuous=continuous(10, 0)),
    ),
    Case(
        INVALID,
        "fusion.deadline_s: … is not between 0 and 30 seconds",
        detect(fusion=detection_pb2.FusionOptions(deadline_s=31)),
    ),
    Case(
        INVALID,
        "fusion: a continuous fused request needs a request stream (DetectStream), whose call carries its "
        "snapshots; DetectObjects takes fused single shots only",
        detect(fusion=detection_pb2.FusionOptions(), continuous=continuous(1, 5)),
    ),
    Case(
        INVALID,
        "report_to_server: set only by the server on its forwards to cameras; a robot asks for fusion instead",
        lambda ch: detection_pb2_grpc.DetectObjectBoundaryStub(ch).DetectObjects(reporting_to_server()),
    ),
    Case(
        "RESOURCE_EXHAUSTED",
        "SERVER: Received message larger than max (… vs. 4194304)",
        detect(robot_id="r" * (5 * 2**20)),
    ),
    Case(INVALID, "camera_id: empty", register(camera_id="")),
    Case(INVALID, "address: '…' is not host:port", register(address="nowhere")),
    Case(INVALID, "homography: missing", register(homography=None)),
    Case(INVALID, "homography: expected 9 numbers (3x3 row-major), got …", register(m=GOOD_H[:8])),
    Case(INVALID, "homography: contains NaN or infinite values", register(m=[math.nan] * 9)),
    Case(INVALID, "homography: all zeros", register(m=[0.0] * 9)),
    Case(
        INVALID,
        "homography: singular (condition number …); it cannot map an image to a floor",
        register(m=[1, 2, 3, 2, 4, 6, 0, 0, 1]),
    ),
    Case(INVALID, "field_of_view: image size …x… is not a real image size", register(image_width=0)),
    Case(INVALID, "field_of_view: max_range_m … must be in (0, 10000]", register(max_range_m=math.nan)),
    Case(
        INVALID,
        "field_of_view: the whole image is above the horizon; the camera sees no floor "
        "(is it pitched up, or is the homography mirrored?)",
        register(m=PITCHED_UP),
    ),
    Case(INVALID, "detector_kinds: empty; a camera must run at least one detector", register(detector_kinds=None)),
    Case(
        NOT_FOUND,
        "camera_id: '…' is not registered",
        lambda ch: registry_pb2_grpc.RegisterVisionServiceStub(ch).Heartbeat(
            registry_pb2.HeartbeatRequest(camera_id="ghost")
        ),
    ),
    Case(
        NOT_FOUND,
        "camera_id: '…' is not registered",
        lambda ch: registry_pb2_grpc.RegisterVisionServiceStub(ch).Deregister(
            registry_pb2.DeregisterRequest(camera_id="ghost")
        ),
    ),
    Case(
        INVALID,
        "region.box: x_lower … must be less than x_upper …",
        lambda ch: registry_pb2_grpc.RegisterVisionServiceStub(ch).ListCameras(
            registry_pb2.ListCamerasRequest(region=box(1, 0, 1, 1))
        ),
    ),
]


#: A mobile camera's mount: 0.8 m up, looking ahead 30° down, 70° wide (its base-frame homography).
MOUNT_H = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0).base_homography((640, 480)).to_list()


def update_pose(**overrides: Any) -> Callable[[Any], Any]:
    """UpdatePose for the registered mobile camera `scout` (its secret filled in unless given)."""

    async def call(ch: Any) -> Any:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(ch)
        message = registry_pb2.UpdatePoseRequest(
            camera_id="scout", registration_secret=SECRETS["scout"], pose=geometry_pb2.Pose2(x=1.0, y=1.0, yaw=0.0)
        )
        for key, value in overrides.items():
            if value is None:
                message.ClearField(key)
            elif key == "pose":
                message.pose.CopyFrom(value)
            else:
                setattr(message, key, value)
        return await stub.UpdatePose(message)

    return call


#: The registrations' secrets in `with_scout`, by camera id.
SECRETS: dict[str, str] = {}
POSE_CASES = [
    Case(
        INVALID,
        "pose_lease_s: … must be >= 0 seconds (0: the server's default)",
        register(camera_id="scout2", m=MOUNT_H, mobile=True, pose_lease_s=-1.0),
    ),
    Case(NOT_FOUND, "camera_id: '…' is not registered", update_pose(camera_id="nobody")),
    Case(
        "FAILED_PRECONDITION",
        "registration_secret: not the current one for camera_id '…': another registration of this id replaced it, "
        "or it never was; register again",
        update_pose(registration_secret="guess"),
    ),
    Case(INVALID, "pose: missing", update_pose(pose=None)),
    Case(INVALID, "pose.x: … is not a finite number", update_pose(pose=geometry_pb2.Pose2(x=math.nan, y=1, yaw=0))),
    Case(INVALID, "pose: (…, …) is beyond ±1e+06 m", update_pose(pose=geometry_pb2.Pose2(x=2e6, y=1, yaw=0))),
    Case(INVALID, "pose_time_unix: … is not a finite number", update_pose(pose_time_unix=math.inf)),
    Case(
        "RESOURCE_EXHAUSTED",
        "pose: camera '…' updated … s ago; at most one update every … s",
        update_pose(pose=geometry_pb2.Pose2(x=1.5, y=1.0, yaw=0.0)),
    ),
]


@pytest_asyncio.fixture
async def with_scout() -> AsyncIterator[tuple[DrvsServer, aio.Channel]]:
    """A server holding a fixed camera `keep` and a mobile camera `scout` that has sent one pose
    (and may send the next only a minute later)."""
    config = ServerConfig(listen="127.0.0.1:0", lease_ttl_s=30, min_pose_interval_s=60)
    async with DrvsServer(config=config) as server, aio.insecure_channel(server.address) as ch:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(ch)
        SECRETS["keep"] = (await stub.Register(registration(camera_id="keep"))).registration_secret
        reply = await stub.Register(registration(camera_id="scout", m=MOUNT_H, mobile=True))
        SECRETS["scout"] = reply.registration_secret
        await update_pose()(ch)
        yield server, ch


@pytest.mark.parametrize("case", POSE_CASES, ids=[f"{c.status}:{c.pattern[:40]}" for c in POSE_CASES])
async def test_mobile_camera_row(with_scout: tuple[DrvsServer, aio.Channel], case: Case) -> None:
    server, channel = with_scout
    regex = documented(case.pattern, case.status)
    before = server.registry.get("scout")
    with pytest.raises(aio.AioRpcError) as err:
        await case.call(channel)
    assert err.value.code().name == case.status, (err.value.code(), err.value.details())
    assert regex.fullmatch(err.value.details() or ""), err.value.details()
    # Nothing changed: the same cameras, the scout's field of view where its accepted pose put it.
    assert sorted(c.camera_id for c in server.registry.cameras()) == ["keep", "scout"]
    assert server.registry.get("scout").field_of_view.equals(before.field_of_view)


async def test_a_fixed_camera_has_no_pose(with_scout: tuple[DrvsServer, aio.Channel]) -> None:
    server, channel = with_scout
    pattern = "camera_id: '…' registered as a fixed camera; it has no pose"
    regex = documented(pattern, "FAILED_PRECONDITION")
    stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
    with pytest.raises(aio.AioRpcError) as err:
        await stub.UpdatePose(
            registry_pb2.UpdatePoseRequest(
                camera_id="keep", registration_secret=SECRETS["keep"], pose=geometry_pb2.Pose2(x=1, y=1)
            )
        )
    assert err.value.code().name == "FAILED_PRECONDITION" and regex.fullmatch(err.value.details() or "")
    assert server.registry.unroutable("keep") == ""


@pytest_asyncio.fixture
async def served() -> AsyncIterator[tuple[DrvsServer, aio.Channel]]:
    async with DrvsServer("127.0.0.1:0", lease_ttl_s=30) as server, aio.insecure_channel(server.address) as ch:
        await registry_pb2_grpc.RegisterVisionServiceStub(ch).Register(registration(camera_id="keep"))
        yield server, ch


@pytest.mark.parametrize("case", GRPC_CASES, ids=[f"{c.status}:{c.pattern[:40]}" for c in GRPC_CASES])
async def test_grpc_row(served: tuple[DrvsServer, aio.Channel], case: Case) -> None:
    server, channel = served
    regex = documented(case.pattern, case.status)
    with pytest.raises(aio.AioRpcError) as err:
        await case.call(channel)
    assert err.value.code().name == case.status, (err.value.code(), err.value.details())
    assert regex.fullmatch(err.value.details() or ""), err.value.details()
    assert [c.camera_id for c in server.registry.cameras()] == ["keep"]  # nothing changed


async def test_streamed_request_row(served: tuple[DrvsServer, aio.Channel]) -> None:
    _, channel = served
    pattern = "request_id: empty; a streamed request needs its own id"
    regex = documented(pattern, INVALID)
    call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectStream()
    await call.write(request(request_id=""))
    await call.done_writing()
    replies = [reply async for reply in call]
    assert replies[0].error.code == INVALID and regex.fullmatch(replies[0].error.message), replies
    assert await call.code() == grpc.StatusCode.OK


# --- the command lines ---------------------------------------------------------------------------


@dataclass(frozen=True)
class CliCase:
    command: str
    args: tuple[str, ...]
    pattern: str
    env: tuple[tuple[str, str], ...] = ()


def cli_cases(tmp: Path) -> list[CliCase]:
    config = tmp / "camera.yaml"
    config.write_text("id: cam1\nsource: x.avi\nhomography: h.yaml\nzoom: 2\n")
    camera = ("--id", "cam1", "--source", "x.avi", "--homography", "h.yaml")
    mobile = ("--id", "cam1", "--source", "x.avi", "--mount", "0,0,0.8,0,30", "--hfov", "70")
    return [
        CliCase("drvs-server", ("--listen", "nowhere"), "listen (--listen, DRVS_SERVER_LISTEN): '…' is not host:port"),
        CliCase(
            "drvs-server", ("--lease-ttl", "0"), "lease_ttl_s (--lease-ttl, DRVS_LEASE_TTL): … must be in (0, 3600]"
        ),
        CliCase(
            "drvs-server", ("--forward-timeout", "100"), "forward_timeout_s (--forward-timeout): … must be in (0, 60]"
        ),
        CliCase(
            "drvs-server",
            ("--allow-callback", "anywhere"),
            "--allow-callback: '…' is not an IP network (e.g. 10.0.0.0/8)",
        ),
        CliCase("drvs-server", ("--rate-limit", "0"), "rate_limit_hz (--rate-limit): … must be in (0, 1e6]"),
        CliCase("drvs-server", ("--max-continuous", "0"), "max_continuous (--max-continuous): … must be in [1, 1e6]"),
        CliCase(
            "drvs-server",
            ("--max-queued-forwards", "0"),
            "max_queued_forwards (--max-queued-forwards): … must be in [1, 100000]",
        ),
        CliCase("drvs-server", ("--workers", "0"), "workers (--workers): … must be in [1, 256] processes"),
        CliCase(
            "drvs-server",
            ("--admission-target", "-1"),
            "admission_target_s (--admission-target): … must be in [0, 10] seconds (0: admission off)",
        ),
        CliCase(
            "drvs-server",
            ("--workers", "2"),
            "workers (--workers): … processes need a shared registry, --registry etcd://HOST:PORT: a camera "
            "registers with one of them and is routed by all",
        ),
        CliCase(
            "drvs-server",
            ("--workers", "2", "--registry", "etcd://127.0.0.1:2379", "--listen", "0.0.0.0:0"),
            "advertise (--advertise, DRVS_SERVER_ADVERTISE): needed with --workers on a wildcard address (…): each "
            "worker takes the reports of its fused requests on a port of its own, at the advertised host",
        ),
        CliCase(
            "drvs-server",
            ("--workers", "2", "--registry", "etcd://127.0.0.1:2379", "--record", "x.mcap"),
            "--workers: the live view and the recording (--foxglove, --record) are one process's; run them on a "
            "single server",
        ),
        CliCase("drvs-camera", ("--config", str(config)), "config FILE: KEY: unknown key (expected one of: …)"),
        CliCase(
            "drvs-camera",
            ("--source", "x.avi", "--homography", "h.yaml"),
            "id: missing; give --id, DRVS_CAMERA_ID or id: in a --config file",
        ),
        CliCase(
            "drvs-camera",
            ("--id", "bad id", "--source", "x.avi", "--homography", "h.yaml"),
            "id (from --id): 'bad id' may hold only letters, digits and - _ . :",
        ),
        CliCase("drvs-camera", (*camera, "--server", "nowhere"), "server (from --server): 'nowhere' is not host:port"),
        CliCase(
            "drvs-camera", (*camera, "--max-range", "0"), "max_range_m (from …): … must be a number from 0.1 to 1000"
        ),
        CliCase(
            "drvs-camera",
            (*camera, "--heartbeat", "0.01"),
            "heartbeat_s (from …): … must be a number from 0.05 to 3600",
        ),
        CliCase(
            "drvs-camera",
            (*camera, "--detectors", "rgb"),
            "detectors (from …): '…' is not an installed detector; installed: …",
        ),
        CliCase(
            "drvs-camera",
            (*camera, "--max-continuous", "0"),
            "max_continuous (from …): … must be a whole number from 1 to 1000000",
        ),
        CliCase(
            "drvs-camera",
            (*camera, "--detect-workers", "0"),
            "detect_workers (from …): … must be a whole number from 1 to 64",
        ),
        CliCase(
            "drvs-camera",
            (*camera, "--people-min-height", "20"),
            "people_min_height_px (from …): … must be a number from 32 to 1024",
        ),
        CliCase(
            "drvs-server",
            ("--max-forward-bytes", "0"),
            "max_forward_bytes_per_s (--max-forward-bytes): … must be in [1, 1e12]",
        ),
        CliCase(
            "drvs-server",
            ("--max-connection-idle", "-1"),
            "max_connection_idle_s (--max-connection-idle): … must be in [0, 1e9] (0: no limit)",
        ),
        CliCase(
            "drvs-server",
            ("--max-pending-calls", "-1"),
            "max_pending_calls (--max-pending-calls): … must be in [0, 1e6] (0: no limit)",
        ),
        CliCase("drvs-server", ("--metrics-port", "nowhere"), "--metrics-port: '…' is not host:port"),
        CliCase("drvs-server", ("--pose-lease", "0"), "pose_lease_s (--pose-lease): … must be in (0, 3600] seconds"),
        CliCase(
            "drvs-server",
            ("--registry", "redis://x:1"),
            "registry (--registry, DRVS_REGISTRY): '…' is not etcd://HOST:PORT[,HOST:PORT...] (or memory)",
        ),
        CliCase(
            "drvs-camera",
            (*camera, "--frame", "floor 1"),
            "frame (--frame): '…' is not ids joined by '/' (letters, digits and - _ . : in each), "
            "e.g. building-a/floor-2",
        ),
        CliCase(
            "drvs-camera",
            (*mobile[:4], "--mount", "0,0,0.8,0", "--hfov", "70"),
            "mount (--mount): '…' is not X,Y,Z,YAW,PITCH (5 finite numbers separated by commas)",
        ),
        CliCase(
            "drvs-camera",
            (*mobile[:4], "--mount", "0,0,0.8,0,30"),
            "mount (--mount): give the camera's --hfov or its --camera-matrix (one of them)",
        ),
        CliCase(
            "drvs-camera",
            (*mobile, "--pose-source", "udp://x:1"),
            "--pose-source: no pose source for …:// (tcp:// is built in)",
        ),
        CliCase(
            "drvs-camera",
            (*mobile, "--max-pose-gap", "0"),
            "max_pose_gap_s (from --max-pose-gap): … must be a number from 0.001 to 60",
        ),
    ]


#: The registration flags (issue 14), run apart so that not every process starts at once.
REGISTRATION_CLI_CASES = [
    CliCase("drvs-server", (), "DRVS_TRUST_NETWORK: '…' is not true or false", (("DRVS_TRUST_NETWORK", "maybe"),)),
    CliCase(
        "drvs-server",
        ("--registration-grace", "-1"),
        "registration_grace_s (--registration-grace): … must be in [0, 86400]",
    ),
    CliCase(
        "drvs-server",
        ("--max-cameras-per-identity", "0"),
        "max_cameras_per_identity (--max-cameras-per-identity): … must be in [1, 1e6]",
    ),
    CliCase(
        "drvs-server", ("--max-fov-range", "5"), "max_fov_range_m (--max-fov-range): … must be in [15, 10000] metres"
    ),
    CliCase(
        "drvs-server", ("--max-fov-area", "0"), "max_fov_area_m2 (--max-fov-area): … must be in [1, 1e8] square metres"
    ),
    CliCase("drvs-server", (), "DRVS_LEASE_TTL: '…' is not a number", (("DRVS_LEASE_TTL", "ten"),)),
]


#: Commands run at once: each imports OpenCV, numpy and shapely, and forty at once on two cores
#: took longer than their 30 s each when the machine was busy.
_CLI_AT_ONCE = 6
_slots: dict[asyncio.AbstractEventLoop, asyncio.Semaphore] = {}


async def run_cli(command: str, args: tuple[str, ...], env: tuple[tuple[str, str], ...] = ()) -> ManagedProcess:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("DRVS_")} | dict(env)
    slots = _slots.setdefault(asyncio.get_running_loop(), asyncio.Semaphore(_CLI_AT_ONCE))
    async with slots:
        proc = await ManagedProcess.entry_point(command, command, *args, env=environ).start()
        try:
            await proc.wait(timeout=30)
        finally:
            await proc.stop()
    return proc


@pytest.mark.parametrize("which", [pytest.param("all", marks=pytest.mark.slow), "registration"])
async def test_command_line_rows(tmp_path: Path, which: str) -> None:
    cases = cli_cases(tmp_path) if which == "all" else REGISTRATION_CLI_CASES
    procs = await asyncio.gather(*(run_cli(c.command, c.args, c.env) for c in cases))
    for case, proc in zip(cases, procs, strict=True):
        regex = documented(case.pattern)
        assert proc.returncode == 2, (case, proc.output())
        last = proc.lines[-1] if proc.lines else ""
        prefix = f"{case.command}: error: "
        assert last.startswith(prefix) and regex.fullmatch(last[len(prefix) :]), (case.pattern, proc.output())


async def test_server_settings_given_as_text_are_validated_too() -> None:
    """The ✘ rows: these end drvs-server with a traceback instead of a usage error naming the setting."""
    cases = [
        (("--listen", "127.0.0.1:0"), (("DRVS_LEASE_TTL", "ten"),), "DRVS_LEASE_TTL"),
        (("--listen", "127.0.0.1:0"), (("DRVS_METRICS_PORT", "ninety"),), "DRVS_METRICS_PORT"),
        (("--listen", "127.0.0.1:0", "--metrics-port", "70000"), (), "--metrics-port"),
    ]
    procs = await asyncio.gather(*(run_cli("drvs-server", args, env) for args, env, _ in cases))
    problems = []
    for (args, env, name), proc in zip(cases, procs, strict=True):
        if proc.returncode != 2 or "Traceback" in proc.output() or name not in proc.lines[-1]:
            problems.append(f"{args} {dict(env)}: exit {proc.returncode}, last line {proc.lines[-1]!r}")
    assert not problems, "\n".join(problems)


def test_every_row_marked_checked_is_checked(tmp_path: Path) -> None:
    checked = {c.pattern for c in GRPC_CASES + POSE_CASES}
    checked |= {c.pattern for c in cli_cases(tmp_path) + REGISTRATION_CLI_CASES}
    checked |= {
        "request_id: empty; a streamed request needs its own id",
        "camera_id: '…' registered as a fixed camera; it has no pose",
    }
    unchecked = [
        r[0] + " " + r[1]
        for r in table_rows()
        if r[-1] == "✓" and not any(p in checked for cell in r[2:-1] for p in quoted(cell))
    ]
    assert not unchecked, f"rows marked ✓ but not checked here: {unchecked}"
