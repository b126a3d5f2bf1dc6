"""The three roles as separate processes over real sockets, on real rendered video."""

from __future__ import annotations

import math
import re

import pytest
from shapely.geometry import box
from shapely.ops import unary_union

from drvs.core.errors import Unavailable
from drvs.robot import DrvsClient
from tests.helpers import BOTH_REGION, CAM1_REGION, CAM2_REGION, OBJECTS, YELLOW, Office, nearest


async def test_region_of_one_camera_reaches_only_that_camera(office: Office) -> None:
    async with DrvsClient(office.address, robot_id="r1") as robot:
        sub = await robot.subscribe(YELLOW, CAM1_REGION, timeout_s=10)
        assert sub.camera_ids == ("cam1",)
        result = await sub.collect()
        assert result.complete and not result.errors
        assert [r.camera_id for r in result.reports] == ["cam1"]
        assert result.reports[0].final and result.reports[0].sequence == 0

        expected = [o for o in OBJECTS if o.filter_def == YELLOW and o.center[0] < 6]
        assert len(result.detections) == len(expected)
        found = set()
        for d in result.detections:
            obj, error = nearest(YELLOW, d.centroid.x, d.centroid.y)
            assert error < 0.03, f"{d.centroid} is {error:.3f} m from {obj.center}"
            x0, y0, x1, y1 = d.bounds
            assert x0 < obj.center[0] < x1 and y0 < obj.center[1] < y1
            assert d.filter_def == YELLOW and d.camera_id == "cam1" and 0 < d.score <= 1
            found.add(obj.center)
        assert found == {o.center for o in expected}

        # cam2 got nothing: it logs every request it receives, in order, so once it has logged a
        # later request, the first one would have been logged before it.
        second = await robot.detect(YELLOW, CAM2_REGION, timeout_s=10)
        assert second.camera_ids == ("cam2",)
        cam2 = office.cameras["cam2"]
        await cam2.wait_for_line(re.escape(second.request_id), timeout=5)
        assert sub.request_id not in cam2.output()


@pytest.mark.slow
async def test_region_over_both_cameras_gets_both(office: Office) -> None:
    async with DrvsClient(office.address, robot_id="r1") as robot:
        result = await robot.detect(YELLOW, BOTH_REGION, timeout_s=10)
    assert sorted(result.camera_ids) == ["cam1", "cam2"]
    assert result.complete and sorted(r.camera_id for r in result.reports) == ["cam1", "cam2"]
    centres = sorted(nearest(YELLOW, d.centroid.x, d.centroid.y)[0].center for d in result.detections)
    assert centres == sorted(o.center for o in OBJECTS if o.filter_def == YELLOW)
    assert max(nearest(YELLOW, d.centroid.x, d.centroid.y)[1] for d in result.detections) < 0.03


@pytest.mark.office_cameras("cam1")
async def test_polygon_region_and_other_colours(office: Office) -> None:
    green = next(o for o in OBJECTS if o.filter_def != YELLOW)
    triangle = [(-0.5, 5.0), (0.5, 5.0), (0.0, 6.5)]
    async with DrvsClient(office.address) as robot:
        result = await robot.detect(green.filter_def, triangle, timeout_s=10)
    assert result.camera_ids == ("cam1",)
    assert len(result.detections) == 1
    assert nearest(green.filter_def, result.detections[0].centroid.x, result.detections[0].centroid.y)[1] < 0.03


@pytest.mark.office_cameras()
async def test_region_seen_by_no_camera_dispatches_nowhere(office: Office) -> None:
    async with DrvsClient(office.address) as robot:
        result = await robot.detect(YELLOW, (100, 100, 101, 101), timeout_s=10)
    assert result.camera_ids == () and result.reports == [] and result.complete


@pytest.mark.slow
async def test_continuous_request_streams_at_its_rate(office: Office) -> None:
    async with DrvsClient(office.address) as robot:
        sub = await robot.subscribe(YELLOW, BOTH_REGION, rate_hz=10, duration_s=1.0, timeout_s=10)
        arrivals: dict[str, list[float]] = {"cam1": [], "cam2": []}
        async for report in sub:
            arrivals[report.camera_id].append(report.capture_time)
        result = sub.result
    assert result.complete
    for camera_id in ("cam1", "cam2"):
        reports = [r for r in result.reports if r.camera_id == camera_id]
        # Ten reports over the second, then the final one at t = 1 s.
        assert 10 <= len(reports) <= 12, [r.sequence for r in reports]
        assert [r.sequence for r in reports] == list(range(len(reports)))
        assert [r.final for r in reports] == [False] * (len(reports) - 1) + [True]
        assert all(len(r.detections) == 2 for r in reports)
        times = arrivals[camera_id]
        assert times == sorted(times)
        assert 0.7 <= times[-1] - times[0] <= 1.5


@pytest.mark.slow
@pytest.mark.office_cameras("cam1")
async def test_robot_that_stops_listening_stops_the_cameras(office: Office) -> None:
    async with DrvsClient(office.address) as robot:
        sub = await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=20, duration_s=30.0, timeout_s=5)
        async for report in sub:
            if report.sequence == 2:
                break  # leaving the loop closes the subscription
        cam1 = office.cameras["cam1"]
        await cam1.wait_for_line(rf"request {sub.request_id} cancelled by the robot", timeout=5)


@pytest.mark.office_cameras("cam1")
async def test_robot_that_closes_mid_request_stops_the_cameras_quietly(office: Office) -> None:
    """A robot that exits with a continuous request still running tells the cameras to stop: they
    do not go on dialling the address it has left, warning for every report."""
    async with DrvsClient(office.address) as robot:
        sub = await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=20, duration_s=30.0, timeout_s=5)
        async for report in sub:
            if report.sequence == 2:
                break_at = len(office.cameras["cam1"].lines)
                break
    cam1 = office.cameras["cam1"]
    await cam1.wait_for_line(rf"request {sub.request_id} cancelled by the robot", timeout=5, start=break_at)
    # The job ends at that line, so nothing later can mention the request. Without the robot's
    # cancellation the camera would instead have dialled the closed listener and warned.
    robot_gone = [line for line in cam1.lines[break_at:] if "WARNING" in line and sub.request_id in line]
    assert robot_gone == [], robot_gone


@pytest.mark.slow
@pytest.mark.timeout(160)  # its own waits (starts, runs, requests) add up to 130 s
async def test_dead_camera_does_not_hold_up_the_other_and_leaves_routing(office: Office) -> None:
    cam2 = office.cameras["cam2"]
    async with DrvsClient(office.address) as robot:
        floors = {c.camera_id: c.field_of_view for c in await robot.cameras()}
        cam1_floor, cam2_floor = floors["cam1"], floors["cam2"]
        cam2.kill()  # a crash: no deregistration
        await cam2.wait()
        result = await robot.detect(YELLOW, BOTH_REGION, timeout_s=10)
        by_camera = {r.camera_id: r for r in result.reports}
        assert len(by_camera["cam1"].detections) == 2 and not by_camera["cam1"].error
        if "cam2" in result.camera_ids:
            # Dispatched before the server knew: it answers for the camera at once.
            assert by_camera["cam2"].final and "cam2" in by_camera["cam2"].error
        # Never a complete answer with nothing there: cam2's part of the floor was not looked at.
        assert not result.complete and result.missing_cameras == {"cam2"}
        assert result.camera_errors["cam2"].code == "UNAVAILABLE"

        await office.server.wait_for_line(r"camera cam2 left routing: lease expired", timeout=10)
        assert [c.camera_id for c in await robot.cameras()] == ["cam1"]
        after = await robot.detect(YELLOW, BOTH_REGION, timeout_s=10)
        # Gone from routing, not from the answer: the server names it and what only it saw.
        assert after.camera_ids == ("cam1",) and not after.complete and after.missing_cameras == {"cam2"}
        error = after.camera_errors["cam2"]
        assert error.code == "UNAVAILABLE" and "lease ran out without it deregistering" in error.message
        cam2_floor = cam2_floor.intersection(box(*BOTH_REGION))
        unseen = unary_union(after.uncovered)  # all the region but cam1's floor, cam2's with it
        assert unseen.covers(cam2_floor.buffer(-0.01)) and not unseen.intersects(cam1_floor.buffer(-0.01))
        assert abs(unseen.area - box(*BOTH_REGION).difference(cam1_floor).area) < 0.01 * unseen.area
        # A region only cam1 sees is complete.
        assert (await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)).complete


async def test_camera_deregisters_on_sigterm(office: Office) -> None:
    cam2 = office.cameras["cam2"]
    assert await cam2.stop() == 0
    await office.server.wait_for_line(r"camera cam2 deregistered", timeout=5)
    async with DrvsClient(office.address) as robot:
        assert [c.camera_id for c in await robot.cameras()] == ["cam1"]


@pytest.mark.slow
@pytest.mark.timeout(180)  # its own waits (starts, runs, requests) add up to 150 s
async def test_cameras_reregister_after_server_restart(office: Office) -> None:
    port = office.address.rsplit(":", 1)[1]
    assert await office.server.stop() == 0
    from drvs.tools.launch import start_server

    office.server, address = await start_server("--lease-ttl", "1.5", "--listen", f"127.0.0.1:{port}")
    assert address == office.address
    for camera_id, proc in office.cameras.items():
        await proc.wait_for_line(rf"camera {camera_id} re-registered", timeout=15)
    async with DrvsClient(office.address) as robot:
        result = await robot.detect(YELLOW, BOTH_REGION, timeout_s=10)
    assert sorted(result.camera_ids) == ["cam1", "cam2"] and result.complete
    assert len(result.detections) == 4


async def test_unreachable_server_fails_fast_with_a_clear_error() -> None:
    async with DrvsClient("127.0.0.1:1") as robot:
        with pytest.raises(Unavailable, match=re.escape("127.0.0.1:1")):
            await robot.detect(YELLOW, CAM1_REGION, timeout_s=1)


@pytest.mark.office_cameras("cam1")
async def test_boxes_only_reports_keep_positions_and_drop_outlines(office: Office) -> None:
    async with DrvsClient(office.address) as robot:
        full = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
        boxes = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10, outlines=False)
    assert len(boxes.detections) == len(full.detections) == 2
    for d in boxes.detections:
        assert d.outline.is_empty
        assert nearest(YELLOW, d.centroid.x, d.centroid.y)[1] < 0.03
    # Two requests may see two different (noisy) frames, whose blobs may differ by a pixel at an
    # edge: the same boxes to within the floor footprint of one pixel there (about 1-2 cm here).
    h = office.recorded["cam1"].homography
    pairs = zip(
        sorted(boxes.detections, key=lambda d: d.bounds), sorted(full.detections, key=lambda d: d.bounds), strict=True
    )
    for a, b in pairs:
        px = a.pixel_box
        corners = [(px.x + dx, px.y + dy) for dx in (0, px.width) for dy in (0, px.height)]
        steps = [(u + du, v + dv) for u, v in corners for du, dv in ((1, 0), (0, 1))]
        floor = h.apply([c for c in corners for _ in (0, 1)])
        pixel_m = max(math.dist(p, q) for p, q in zip(floor, h.apply(steps), strict=True))
        assert max(abs(u - v) for u, v in zip(a.bounds, b.bounds, strict=True)) <= 1.5 * pixel_m, pixel_m
