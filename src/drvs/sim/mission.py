"""One run of the simulated robot (drvs-office's robot process): its mission against the world, and
result.json.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc

from drvs.core.model import Detection
from drvs.robot import DrvsClient
from drvs.sim.planner import NoPath
from drvs.sim.robot import MissionFailed, SimRobot
from drvs.tools.meter import MeteredClient
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire import _grpc
from drvs.wire.security import Security


def detection_record(d: Detection) -> dict[str, Any]:
    record: dict[str, Any] = {
        "filter_def": d.filter_def,
        "camera_id": d.camera_id,
        # Which cameras saw it (a fused object: every camera whose reports it merges).
        "camera_ids": d.camera_id.split(",") if d.camera_id else [],
        "bounds": [round(v, 4) for v in d.bounds],
        "centroid": [round(d.centroid.x, 4), round(d.centroid.y, 4)],
        "outline": [[round(x, 4), round(y, 4)] for x, y in list(d.outline.exterior.coords)[:-1]],
    }
    if d.marker_id is not None:
        record["marker_id"] = d.marker_id
    if d.heading_deg is not None:
        record["heading_deg"] = round(d.heading_deg, 2)
    return record


async def run_robot(
    world_address: str,
    server_address: str | None,
    out_dir: Path,
    *,
    progress: Callable[[dict[str, Any]], None],
    max_time_s: float = 120.0,
    security: Security | None = None,
    detector: str = "hsv",
    delivery: str = "fused",
    predict: bool = True,
    live: str | None = None,
) -> dict[str, Any]:
    from drvs.sim.scenario import parse_scenario

    cpu_start = time.process_time()
    async with _grpc.insecure_channel(world_address) as channel:
        world = sim_pb2_grpc.SimulatedWorldStub(channel)
        scene = await world.GetScene(sim_pb2.GetSceneRequest(), timeout=10, wait_for_ready=True)
        scenario = parse_scenario(scene.scenario_yaml, f"world {world_address}")
        # The robot's two connections pass through counting relays: bytes_to_robot and
        # wire_bytes_to_robot are what its sockets received (drvs.tools.meter).
        metered = MeteredClient(server_address, robot_id="sim-robot", security=security) if server_address else None
        client: DrvsClient | None = None
        try:
            if metered is not None:
                client = await metered.start()
            robot = SimRobot(
                scenario,
                world,
                client,
                progress=progress,
                max_time_s=max_time_s,
                detector=detector,
                delivery=delivery,
                predict=predict,
            )
            if live:
                from drvs.sim.robot_view import RobotView

                robot.view = RobotView(live, scenario.robot.radius)
                await robot.view.start()
            mission = getattr(robot, scenario.mission)
            try:
                outcome = await mission()
                failure = None
            except (MissionFailed, NoPath, grpc.RpcError) as exc:
                outcome = {"reached_goal": False, "charging_station": None, "candidates": []}
                failure = str(exc)
            robot.report_progress(force=True)
            if robot.view is not None:
                await robot.view.close()
            received = metered.payload_bytes()[0] if metered is not None else 0
            wire_received = metered.ethernet_bytes()[0] if metered is not None else 0
        finally:
            if metered is not None:
                await metered.close()
    errors = robot.localisation_errors
    headings = robot.heading_errors
    result: dict[str, Any] = {
        "scenario": scenario.name,
        "mission": scenario.mission,
        "drvs": client is not None,
        "detector": detector,
        "delivery": delivery if client is not None else None,
        "predict": predict,
        **outcome,
        "collisions": robot.collisions,
        "overload_refusals": robot.overload_refusals,
        "replans": robot.replans,
        "path": [[round(x, 4), round(y, 4)] for x, y in robot.path_driven],
        "planned_paths": [[[round(x, 3), round(y, 3)] for x, y in p] for p in robot.plans],
        "detections": sorted(
            (detection_record(d) for d in robot.detections_used), key=lambda r: (r["camera_id"], r["centroid"])
        ),
        "contacts": [[[round(x, 4), round(y, 4)] for x, y in list(c.exterior.coords)[:-1]] for c in robot.contacts],
        "localisation": {
            "fixes": len(errors),
            "mean_error_m": round(sum(errors) / len(errors), 4) if errors else None,
            "max_error_m": round(max(errors), 4) if errors else None,
            "filter_def": robot.self_filter,
            "mean_heading_error_deg": round(sum(headings) / len(headings), 3) if headings else None,
            "max_heading_error_deg": round(max(headings), 3) if headings else None,
        },
        "tracks": [r.summary(robot._epoch) for r in robot.tracks.values() if r.snapshots > 1 or r.moving],
        "wait_steps": robot.wait_steps,
        "world_time_s": round(robot.world_time_s, 3),
        "coverage_events": robot.coverage_events,
        "blind_steps": robot.blind_steps,
        "reports_rejected": client.reports_rejected if client is not None else 0,
        "bytes_to_robot": received,
        "wire_bytes_to_robot": wire_received,
        "robot_cpu_s": round(time.process_time() - cpu_start, 3),
        "elapsed_s": round(time.monotonic() - robot._started, 2),
    }
    if robot.view is not None:
        # What the robot published into the live view (0: it could not reach it, and went on without).
        result["live_view"] = {"url": robot.view.url, "published": robot.view.sent}
    if failure:
        result["failure"] = failure
    await asyncio.to_thread(write_result, out_dir, result)
    return result


def write_result(out_dir: Path, result: dict[str, Any]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "result.json").write_text(json.dumps(result, indent=1) + "\n")
