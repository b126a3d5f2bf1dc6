"""Shared fixtures: a recorded two-camera floor, and DRVS roles started as real processes."""

from __future__ import annotations

import math
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import pytest_asyncio

from drvs.filters import HsvRange
from drvs.geometry import homography_from_pose
from drvs.launch import ManagedProcess, start_camera, start_server
from drvs.sim.scene import FloorPatch, RecordedCamera, record_camera

YELLOW = "hsv_014110130035225200"
GREEN = "hsv_040080080080255255"
IMAGE_SIZE = (640, 480)
#: Fields of view: cam1 sees about x -3.8..3.8, y 1.5..7.5; cam2 the same 20 m further along x.
CAMERA_POSES = {"cam1": (0.0, 0.0, 3.0), "cam2": (20.0, 0.0, 3.0)}
CAM1_REGION = (-6.0, 0.0, 6.0, 10.0)
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


@pytest.fixture(scope="session")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, RecordedCamera]:
    """Two cameras' video files of the same floor, with their homography files."""
    directory: Path = tmp_path_factory.mktemp("floor")
    patches = [FloorPatch.disc(o.center, o.radius, HsvRange.parse(o.filter_def).centre_bgr()) for o in OBJECTS]
    out = {}
    for seed, (camera_id, position) in enumerate(CAMERA_POSES.items()):
        h = homography_from_pose(position, 90.0, 40.0, 60.0, IMAGE_SIZE)
        out[camera_id] = record_camera(directory, camera_id, h, IMAGE_SIZE, patches, seed=seed)
    return out


@dataclass
class Office:
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


async def start_office(recorded: dict[str, RecordedCamera], lease_ttl: float) -> Office:
    server, address = await start_server("--lease-ttl", str(lease_ttl))
    office = Office(server, address, {}, recorded)
    try:
        for camera_id in recorded:
            await office.start_camera(camera_id)
    except BaseException:
        await stop_office(office)
        raise
    return office


async def stop_office(office: Office) -> None:
    for proc in office.cameras.values():
        await proc.stop()
    await office.server.stop()


@pytest_asyncio.fixture
async def office(recorded: dict[str, RecordedCamera]) -> AsyncIterator[Office]:
    """drvs-server and two drvs-camera processes, lease 1.5 s; all reaped afterwards."""
    o = await start_office(recorded, lease_ttl=1.5)
    try:
        yield o
    finally:
        await stop_office(o)
