"""Object types end to end, with real processes: a camera registers the types it serves, the server
routes a request only to cameras that serve its type, a type nobody serves is refused by name, a
malformed filter_def is refused naming the wrong part, and a detector plug-in installed from
outside the drvs package (an entry point, as a third party would ship it) runs in a real camera."""

from __future__ import annotations

import asyncio
import json
import math
import os
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio

from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, start_server
from tests.fakes import start_recorded_camera
from tests.helpers import CAM1_REGION, OBJECTS, YELLOW, metrics_port, scrape

PLUGINS = Path(__file__).parents[1] / "plugins"


def plugin_env(tmp: Path) -> dict[str, str]:
    """An environment in which Python finds tests/plugins/drvs_test_colours.py as an installed
    package's "drvs.detectors" entry points (a .dist-info beside it, as pip would write)."""
    site = tmp / "site"
    info = site / "drvs_test_colours-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: drvs-test-colours\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[drvs.detectors]\ncolours = drvs_test_colours\n")
    path = os.pathsep.join([str(site), str(PLUGINS), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path}


class Floor:
    def __init__(self, server: ManagedProcess, address: str, cameras: list[ManagedProcess]) -> None:
        self.server, self.address, self.cameras = server, address, cameras


@pytest_asyncio.fixture
async def floor(recorded: dict[str, RecordedCamera], tmp_path: Path) -> AsyncIterator[Floor]:
    """A server and two cameras on the same view: `colour` runs only hsv; `plug` runs hsv and the
    plug-in's `yellowish` (the plug-in also offers `greenish`, which no camera runs)."""
    env = plugin_env(tmp_path)
    rec = recorded["cam1"]
    server, address = await start_server(env=env)
    floor = Floor(server, address, [])
    try:
        for camera_id, detectors in (("colour", "hsv"), ("plug", "hsv,yellowish")):
            floor.cameras.append(
                await start_recorded_camera(camera_id, rec, address, "--detectors", detectors, env=env)
            )
        yield floor
    finally:
        for proc in floor.cameras:
            await proc.stop()
        await server.stop()


async def test_requests_go_only_to_cameras_that_serve_their_type(floor: Floor) -> None:
    async with DrvsClient(floor.address, robot_id="r1") as client:
        kinds = {c.camera_id: set(c.detector_kinds) for c in await client.cameras()}
        assert kinds == {"colour": {"hsv"}, "plug": {"hsv", "yellowish"}}

        colour = await client.detect(YELLOW, CAM1_REGION, timeout_s=20)
        assert sorted(colour.camera_ids) == ["colour", "plug"] and colour.complete

        plugged = await client.detect("yellowish_30", CAM1_REGION, timeout_s=20)
        assert plugged.camera_ids == ("plug",) and plugged.complete
        # The plug-in's own code found the yellow discs on the real pixels; the common code mapped them.
        yellow = [o for o in OBJECTS if o.filter_def == YELLOW and o.center[0] < 5]
        assert len(plugged.detections) == len(yellow)
        for d in plugged.detections:
            assert d.label == "yellowish" and d.filter_def == "yellowish_30"
            assert min(math.dist(d.centroid_xy, o.center) for o in yellow) < 0.15

        with pytest.raises(FailedPrecondition, match=r"filter_def: no camera serves 'greenish' .*'greenish_30'"):
            await client.detect("greenish_30", CAM1_REGION, timeout_s=20)
        with pytest.raises(InvalidArgument, match=r"filter_def: 'yellowish_x' is not 'yellowish_' and a minimum"):
            await client.detect("yellowish_x", CAM1_REGION, timeout_s=20)
        with pytest.raises(InvalidArgument, match=r"filter_def: unknown object type 'purple' .*known types: hsv"):
            await client.detect("purple_1", CAM1_REGION, timeout_s=20)


@pytest.mark.slow
async def test_drvs_robot_cameras_shows_each_cameras_types(floor: Floor) -> None:
    proc = await ManagedProcess.entry_point("robot", "drvs-robot", "cameras", "--server", floor.address).start()
    assert await proc.wait() == 0, proc.output()
    lines = {line.split()[0]: line for line in proc.lines if line.strip()}
    assert lines["colour"].endswith("serves hsv") and lines["plug"].endswith("serves hsv,yellowish"), proc.output()
    proc = await ManagedProcess.entry_point(
        "robot", "drvs-robot", "cameras", "--json", "--server", floor.address
    ).start()
    assert await proc.wait() == 0, proc.output()
    rows = {r["camera_id"]: r["detector_kinds"] for r in map(json.loads, proc.lines)}
    assert rows == {"colour": ["hsv"], "plug": ["hsv", "yellowish"]}


async def test_a_camera_asked_for_a_detector_that_is_not_installed_stops_at_start(
    recorded: dict[str, RecordedCamera],
) -> None:
    rec = recorded["cam1"]
    proc = await ManagedProcess.entry_point(
        "cam",
        "drvs-camera",
        "--id",
        "cam",
        "--source",
        str(rec.video),
        "--homography",
        str(rec.homography_file),
        "--server",
        "127.0.0.1:1",
        "--detectors",
        "hsv,yellowish",  # the plug-in is not on this process's path
    ).start()
    assert await proc.wait() == 2 and "Traceback" not in proc.output(), proc.output()
    message = "drvs-camera: error: detectors (from --detectors): 'yellowish' is not an installed detector"
    assert any(line.startswith(message) and "installed: hsv" in line for line in proc.lines), proc.output()


@pytest_asyncio.fixture
async def slow(recorded: dict[str, RecordedCamera], tmp_path: Path) -> AsyncIterator[tuple[str, int]]:
    """A server and one camera running only the plug-in's heavy `slowyellowish`, with metrics:
    (server address, the camera's metrics port)."""
    env = plugin_env(tmp_path)
    rec = recorded["cam1"]
    server, address = await start_server(env=env)
    camera = None
    try:
        camera = await start_recorded_camera(
            "slow", rec, address, "--detectors", "slowyellowish", "--metrics-port", "0", env=env
        )
        await camera.wait_for_line(r"metrics on http://")
        yield address, metrics_port(camera)
    finally:
        if camera is not None:
            await camera.stop()
        await server.stop()


async def test_requests_for_a_frame_being_searched_by_a_heavy_detector_share_that_search(
    slow: tuple[str, int],
) -> None:
    """Heavy detectors run in the camera's bounded pool, and a request that arrives while a search
    is running takes its result: eight requests at once cost one search, counted by the camera's
    own drvs_detector_runs_total."""
    address, port = slow
    runs = 'drvs_detector_runs_total{detector="slowyellowish"}'
    assert (await scrape(port)).get(runs, 0.0) == 0.0
    async with DrvsClient(address, robot_id="r1") as client:
        results = await asyncio.gather(
            *(client.detect("slowyellowish_30", CAM1_REGION, timeout_s=30) for _ in range(8))
        )
    for result in results:
        assert result.complete and len(result.detections) == 2, result.camera_errors
    after = await scrape(port)
    assert after[runs] == 1.0, after[runs]
    assert len({r.reports[0].capture_time for r in results}) == 1  # all from the one frame searched


@pytest.mark.slow
async def test_continuous_requests_share_the_heavy_search_that_is_running(slow: tuple[str, int]) -> None:
    """Six robots following people at 10 Hz: each report needs a search of a few hundred ms, on a
    newer frame each time. A request that comes while a search runs takes that search's result
    rather than queue its own behind it, so the camera runs about one search per search time, not
    one per report (which would also make every answer wait in the queue)."""
    address, port = slow
    async with DrvsClient(address, robot_id="r1") as client:
        results = await asyncio.gather(
            *(
                client.detect("slowyellowish_30", CAM1_REGION, rate_hz=10, duration_s=2.0, timeout_s=30)
                for _ in range(6)
            )
        )
    reports = sum(len(r.reports) for r in results)
    for result in results:
        assert result.complete and all(len(r.detections) == 2 for r in result.reports), result.camera_errors
    runs = (await scrape(port))['drvs_detector_runs_total{detector="slowyellowish"}']
    assert reports >= 6 * 3 and runs <= reports / 3.5, (runs, reports)
