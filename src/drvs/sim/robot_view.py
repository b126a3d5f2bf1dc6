"""The office robot in the live view: its pose, the path it plans and the path it has driven,
published into the server's Foxglove live view over the Foxglove WebSocket protocol (clientPublish),
as any robot could publish its own. The server shows them and records them with the rest.

Topics: /robot/pose (foxglove.PoseInFrame) and /robot/paths (foxglove.SceneUpdate: the robot's body,
its planned path and, once a second, the whole path it drove), at most `RATE_HZ` times a second.
What it costs the robot is measured by `drvs-bench liveview`. The view must never cost the mission:
a view that cannot be reached is logged once and the robot carries on without it."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Sequence

from drvs.live import liveview as lv
from drvs.live.foxglove_client import FoxgloveClient

log = logging.getLogger("drvs.sim.robot_view")

RATE_HZ = 5.0
#: The path driven (which grows) goes with every this-many-th update; the planned path starts where
#: the robot is, so the view stays joined up between.
TRAIL_EVERY = 5
#: The driven path keeps a point only this far from the last one kept.
TRAIL_STEP_M = 0.03


class RobotView:
    def __init__(self, url: str, radius_m: float, robot_id: str = "sim-robot") -> None:
        self.url = url
        self.radius_m = radius_m
        self.robot_id = robot_id
        self.trail: list[tuple[float, float]] = []
        self._state: tuple[tuple[float, float], float, tuple[tuple[float, float], ...]] | None = None
        self._changed = asyncio.Event()
        self._client: FoxgloveClient | None = None
        self._task: asyncio.Task[None] | None = None
        self.sent = 0

    async def start(self) -> None:
        from foxglove.messages import PoseInFrame, SceneUpdate

        try:
            self._client = await FoxgloveClient.connect(self.url, timeout=5.0)
            pose_schema, scene_schema = PoseInFrame.get_schema(), SceneUpdate.get_schema()
            self._pose = await self._client.advertise(
                "/robot/pose", "protobuf", pose_schema.name, pose_schema.data, "protobuf"
            )
            self._paths = await self._client.advertise(
                "/robot/paths", "protobuf", scene_schema.name, scene_schema.data, "protobuf"
            )
        except (OSError, ConnectionError, TimeoutError) as exc:
            log.warning("live view %s: cannot publish the robot there (%s); carrying on without it", self.url, exc)
            self._client = None
            return
        self._task = asyncio.get_running_loop().create_task(self._run())

    def update(self, pose: tuple[float, float], heading: float, plan: Sequence[tuple[float, float]]) -> None:
        if not self.trail or math.dist(self.trail[-1], pose) >= TRAIL_STEP_M:
            self.trail.append(pose)
        self._state = (pose, heading, tuple(plan))
        self._changed.set()

    async def _run(self) -> None:
        assert self._client is not None
        try:
            while True:
                await self._changed.wait()
                self._changed.clear()
                if self._state is not None:
                    pose_msg, paths_msg = self._messages(*self._state, trail=self.sent % TRAIL_EVERY == 0)
                    await self._client.publish(self._pose, pose_msg)
                    await self._client.publish(self._paths, paths_msg)
                    self.sent += 1
                await asyncio.sleep(1.0 / RATE_HZ)
        except Exception as exc:  # the view went away: the mission goes on
            log.warning("live view %s: stopped publishing the robot (%s)", self.url, exc)

    def _messages(
        self, pose: tuple[float, float], heading: float, plan: tuple[tuple[float, float], ...], trail: bool = True
    ) -> tuple[bytes, bytes]:
        from foxglove.messages import CylinderPrimitive, Pose, PoseInFrame, SceneEntity, Vector3

        x, y = pose
        where = Pose(position=Vector3(x=x, y=y, z=0.0), orientation=lv.heading_quaternion(heading))
        pose_msg = PoseInFrame(timestamp=lv.stamp(), frame_id=lv.FRAME, pose=where)
        d = 2 * self.radius_m
        body = SceneEntity(
            timestamp=lv.stamp(),
            frame_id=lv.FRAME,
            id=f"robot/{self.robot_id}",
            cylinders=[
                CylinderPrimitive(
                    pose=Pose(position=Vector3(x=x, y=y, z=0.15), orientation=lv.heading_quaternion(heading)),
                    size=Vector3(x=d, y=d, z=0.3),
                    bottom_scale=1.0,
                    top_scale=1.0,
                    color=lv.rgba(0.1, 0.75, 0.3, 0.9),
                )
            ],
            texts=[lv.text(self.robot_id, x, y, lv.rgba(0.1, 0.5, 0.2), z=0.5)],
        )
        planned = SceneEntity(
            timestamp=lv.stamp(),
            frame_id=lv.FRAME,
            id=f"robot/{self.robot_id}/planned",
            lines=[lv.line(plan, lv.rgba(0.1, 0.8, 0.3, 0.9), z=0.06, width=0.05)] if len(plan) > 1 else [],
        )
        if not trail:
            return pose_msg.encode(), lv.scene([body, planned]).encode()
        driven = SceneEntity(
            timestamp=lv.stamp(),
            frame_id=lv.FRAME,
            id=f"robot/{self.robot_id}/driven",
            lines=[lv.line([*self.trail, pose], lv.rgba(0.9, 0.4, 0.1, 0.9), z=0.05, width=0.04)],
        )
        return pose_msg.encode(), lv.scene([body, planned, driven]).encode()

    async def close(self) -> None:
        if self._task is not None:
            if self._state is not None and self._client is not None:
                with contextlib.suppress(Exception):  # the last pose, so the view ends where the robot did
                    pose_msg, paths_msg = self._messages(*self._state)
                    await self._client.publish(self._pose, pose_msg)
                    await self._client.publish(self._paths, paths_msg)
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self._client is not None:
            with contextlib.suppress(Exception):
                await self._client.close()
