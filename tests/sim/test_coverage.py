"""Coverage is part of every answer: the part of a request's region that no camera the server asked
sees comes back as `uncovered` on every path (per-camera single shots and continuous requests,
fused single shots and tracks, DetectObjects and DetectStream, drvs-robot detect), also when no
camera was dispatched at all, so that a robot never reads unseen floor as "nothing there"."""

from __future__ import annotations

import json

import grpc
import pytest
from grpc import aio
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from drvs import DrvsClient
from drvs.sim.robot import DELIVERIES, SimRobot
from drvs.sim.scenario import load_scenario
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from drvs.wire.convert import polygon_from_pb
from tests.helpers import CAM1_REGION, YELLOW, Office, detect_message, roi, run_robot

#: Far from both cameras: nobody sees any of it.
NOWHERE = (40.0, 0.0, 45.0, 5.0)


def same_area(parts: list[Polygon] | tuple[Polygon, ...], expected: Polygon) -> bool:
    """`parts` cover `expected`, give or take 1 %."""
    return bool(unary_union(list(parts)).symmetric_difference(expected).area < 0.01 * max(expected.area, 1.0))


@pytest.mark.office_cameras("cam1")
async def test_every_python_answer_carries_what_no_camera_sees(office: Office) -> None:
    async with DrvsClient(office.address) as robot:
        (cam1,) = await robot.cameras()
        region = box(*CAM1_REGION)
        unseen = region.difference(cam1.field_of_view)  # CAM1_REGION reaches past cam1's floor
        inside = cam1.field_of_view.buffer(-0.5)  # all of it seen

        # Per-camera single shot: cam1 answered (complete), but not all of the region was seen.
        shot = await robot.detect(YELLOW, CAM1_REGION, timeout_s=5)
        assert shot.camera_ids == ("cam1",) and shot.complete and not shot.all_seen
        assert same_area(shot.uncovered, unseen) and all(not p.interiors for p in shot.uncovered)
        seen = await robot.detect(YELLOW, inside, timeout_s=5)
        assert seen.complete and seen.uncovered == [] and seen.all_seen

        # A region no camera sees: nothing dispatched, and all of it uncovered (not "nothing there").
        far = await robot.detect(YELLOW, NOWHERE, timeout_s=5)
        assert far.camera_ids == () and far.reports == [] and not far.all_seen
        assert same_area(far.uncovered, box(*NOWHERE))

        # A continuous request says it in its reply too.
        async with robot.subscribe(YELLOW, CAM1_REGION, rate_hz=10, duration_s=0.2) as sub:
            async for _ in sub:
                pass
        assert same_area(sub.result.uncovered, unseen) and not sub.result.all_seen

        # Fused single shot, and the snapshots of a track.
        snapshot = await robot.snapshot(YELLOW, CAM1_REGION, timeout_s=5)
        assert snapshot.camera_ids == ("cam1",) and same_area(snapshot.uncovered, unseen) and not snapshot.all_seen
        assert (await robot.snapshot(YELLOW, inside, timeout_s=5)).all_seen
        nobody = await robot.snapshot(YELLOW, NOWHERE, timeout_s=5)
        assert nobody.objects == () and same_area(nobody.uncovered, box(*NOWHERE))
        async with robot.track(YELLOW, CAM1_REGION, rate_hz=10, duration_s=0.3) as track:
            snapshots = [s async for s in track]
        assert snapshots and all(same_area(s.uncovered, unseen) for s in snapshots)

        # A frame no camera is in: the whole region.
        robot.frame = "nowhere"
        other = await robot.detect(YELLOW, inside, timeout_s=5)
        assert other.camera_ids == () and same_area(other.uncovered, inside)


@pytest.mark.office_cameras("cam1")
async def test_detect_objects_and_detect_stream_carry_uncovered(office: Office) -> None:
    far = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=40, y_lower=0, x_upper=45, y_upper=5))
    async with aio.insecure_channel(office.address) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        reply = await stub.DetectObjects(detect_message(region=far))
        unseen = [polygon_from_pb(p, "uncovered") for p in reply.uncovered]
        assert list(reply.camera_ids) == [] and same_area(unseen, box(*NOWHERE))
        call = stub.DetectStream()
        await call.write(detect_message(region=far, request_id="s-1"))
        streamed = await call.read()
        assert isinstance(streamed, detection_pb2.DetectionReply) and streamed.request_id == "s-1"
        assert same_area([polygon_from_pb(p, "uncovered") for p in streamed.uncovered], box(*NOWHERE))
        await call.done_writing()
        assert await call.code() == grpc.StatusCode.OK


@pytest.mark.office_cameras("cam1")
async def test_drvs_robot_detect_fails_when_some_of_the_region_went_unseen(office: Office) -> None:
    server = ("--server", office.address, "--filter", YELLOW)
    # A frame no camera is in: exit 3, and with --json a last object saying what went unseen.
    code, lines = await run_robot("detect", *server, "--roi", roi(NOWHERE), "--frame", "nowhere", "--json")
    assert code == 3, lines
    (out,) = [json.loads(line) for line in lines if line.startswith("{")]
    assert out["complete"] is True and out["missing_cameras"] == [] and out["request_id"]
    assert same_area([Polygon(p) for p in out["uncovered"]], box(*NOWHERE)) and out["uncovered_m2"] == 25.0
    # The same as text: exit 3, and how much went unseen on stderr.
    code, lines = await run_robot("detect", *server, "--roi", roi(NOWHERE))
    assert code == 3 and any("25.0 m² of the region unseen" in line for line in lines), lines
    # Fused: the snapshot's JSON names it, and exit 3.
    code, lines = await run_robot("detect", *server, "--roi", roi(NOWHERE), "--fuse", "--json")
    assert code == 3, lines
    (snapshot,) = [json.loads(line) for line in lines if line.startswith("{")]
    assert snapshot["objects"] == [] and same_area([Polygon(p) for p in snapshot["uncovered"]], box(*NOWHERE))


@pytest.mark.office_cameras("cam1")
async def test_the_simulated_robot_treats_uncovered_floor_as_unknown(office: Office) -> None:
    """The simulated robot's look along its way, fused and per camera: floor the answer says no
    camera sees is where it creeps (its blind area), as where a missing camera looked."""
    async with DrvsClient(office.address) as drvs:
        (cam1,) = await drvs.cameras()
        region = box(*CAM1_REGION)
        for delivery in DELIVERIES:
            robot = SimRobot(load_scenario(), None, drvs, delivery=delivery)
            robot.fields_of_view = {cam1.camera_id: cam1.field_of_view}
            await robot.look([YELLOW], region)
            blind = robot.blind_area()
            assert blind is not None and same_area([blind], region.difference(cam1.field_of_view)), delivery
            await robot.look([YELLOW], cam1.field_of_view.buffer(-0.5))  # all seen: nothing unknown
            assert robot.blind_area() is None, delivery
