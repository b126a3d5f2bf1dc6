"""drvs-bench mobile --parts staleness: how old the field of view a server routes a mobile camera
by is, end to end.

A real drvs-server process and a mobile camera node (`CameraNode` with a mount, in this process,
as a robot's own code runs it) whose robot drives a straight line at 0.5 and at 1.0 m/s, its
localisation pushing 20 poses a second. The node sends the server its pose as it does for any
robot (when it has moved 0.1 m or turned 5°, at most 5 times a second, or when the last one is half
a pose lease old). A robot asks the server for the camera 20 times a second (`ListCameras`, what
routing reads) and notes the pose the server holds: its staleness is the time since the robot was
at that pose. That covers the node's thresholds and rate cap, the network, and the server.
"""

from __future__ import annotations

import asyncio
import statistics
import time
from typing import Any

import numpy as np

from drvs.camera import CameraNode, PushSource
from drvs.core.mobile import Mount
from drvs.core.model import Pose2
from drvs.robot import DrvsClient
from drvs.tools.launch import start_server

from .helpers import percentile

SPEEDS_MPS = (0.5, 1.0)
POSE_RATE_HZ = 20.0
SAMPLE_RATE_HZ = 20.0
MOUNT = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0)


async def one_drive(address: str, speed: float, seconds: float, camera_id: str) -> list[float]:
    """Staleness samples (seconds) of one drive at `speed`."""
    source = PushSource("bench camera")
    blank = np.zeros((480, 640, 3), np.uint8)
    source.push(blank)
    node = CameraNode(camera_id, source, None, address, mount=MOUNT, detectors=("hsv",))
    pushed: dict[tuple[float, float, float], float] = {}
    samples: list[float] = []
    async with node, DrvsClient.connect(address, robot_id="bench") as drvs:
        await asyncio.wait_for(node.registered.wait(), 30)
        start = time.time()

        async def drive() -> None:
            k = 0
            while (now := time.time()) - start < seconds:
                pose = Pose2(1.0 + speed * (now - start), 2.0, 0.0)
                pushed[(pose.x, pose.y, pose.yaw)] = now
                node.push_pose(pose, now)
                source.push(blank, now)  # a camera that delivers frames (one that stops is taken out of service)
                k += 1
                await asyncio.sleep(max(0.0, start + k / POSE_RATE_HZ - time.time()))

        driving = asyncio.get_running_loop().create_task(drive())
        try:
            k = 0
            while not driving.done():
                k += 1
                await asyncio.sleep(max(0.0, start + 1.0 + k / SAMPLE_RATE_HZ - time.time()))  # after 1 s of driving
                now = time.time()
                mine = [c for c in await drvs.cameras() if c.camera_id == camera_id]
                if mine and mine[0].pose is not None and not mine[0].unroutable:
                    p = mine[0].pose
                    at = pushed.get((p.x, p.y, p.yaw))
                    if at is not None:
                        samples.append(now - at)
        finally:
            await driving
    return samples


async def staleness(quick: bool) -> dict[str, Any]:
    seconds = 4.0 if quick else 10.0
    rounds = 2 if quick else 3
    proc, address = await start_server("--min-pose-interval", "0.05")
    try:
        result: dict[str, Any] = {"seconds_per_drive": seconds, "rounds": rounds, "speeds": {}}
        for speed in SPEEDS_MPS:
            p50s, p95s, maxes, counts = [], [], [], []
            for r in range(rounds):
                s = await one_drive(address, speed, seconds, f"scout-{speed:g}-{r}")
                if not s:
                    raise RuntimeError(f"no staleness sample at {speed} m/s: the server never held a pose pushed")
                p50s.append(1000 * statistics.median(s))
                p95s.append(1000 * percentile(s, 95))
                maxes.append(1000 * max(s))
                counts.append(len(s))
            result["speeds"][f"{speed:g}"] = {
                "samples": counts,
                "staleness_ms_p50": statistics.median(p50s),
                "staleness_ms_p50_spread": [min(p50s), max(p50s)],
                "staleness_ms_p95": statistics.median(p95s),
                "staleness_ms_p95_spread": [min(p95s), max(p95s)],
                "staleness_ms_max": max(maxes),
                # How far behind the robot the routed field of view is, at the p95 staleness.
                "lag_m_p95": speed * statistics.median(p95s) / 1000,
            }
        return result
    finally:
        await proc.stop()


def run_staleness(quick: bool) -> dict[str, Any]:
    return asyncio.run(staleness(quick))
