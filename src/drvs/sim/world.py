"""The simulated world: robot pose, bumper contacts and docking, served over gRPC."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import grpc
import shapely
from grpc import aio
from shapely import STRtree
from shapely.geometry import Point, Polygon, box

from drvs.core.errors import DrvsError, InvalidArgument, Unavailable
from drvs.core.net import parse_address
from drvs.sim.scenario import Scenario, ScenarioError, load_scenario, parse_scenario
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire import _grpc
from drvs.wire._cli import setup_logging, shutdown_event
from drvs.wire._service import Endpoint, Lifecycle
from drvs.wire.convert import polygon_to_pb

log = logging.getLogger("drvs.sim.world")

SERVICE_NAMES = (sim_pb2.DESCRIPTOR.services_by_name["SimulatedWorld"].full_name,)
#: Moves are checked for contact every this many metres.
CONTACT_STEP_M = 0.01
#: The robot docks when its centre is this close to a charging station's centre.
DOCK_REACH_M = 0.3
#: A scout's poses a second when WatchScout asks for none, and the most it may ask for.
DEFAULT_SCOUT_RATE_HZ = 20.0
MAX_SCOUT_RATE_HZ = 200.0


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    theta: float = 0.0
    version: int = 0
    #: When the world's clock started, seconds since the Unix epoch; 0.0 while it has not.
    clock_start: float = 0.0


class WorldState:
    """The truth: where the robot is and what it would touch. Pure logic.

    World time starts at the mission's start (`start_clock`, or the first move): a moving obstacle
    is where its path puts it at world time, for the cameras and for the bumper alike."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        sx, sy = scenario.robot.start
        self.pose = Pose(sx, sy, 0.0, 0)
        self.radius = scenario.robot.radius
        outside = box(*scenario.bounds).buffer(50.0, join_style="mitre").difference(box(*scenario.bounds))
        still = [o.shape for o in scenario.obstacles if not o.moving]
        self.solids: list[Polygon] = [*scenario.walls, *still, outside]
        self._tree = STRtree(self.solids)
        self.moving = scenario.moving_obstacles
        self.collisions = 0
        self.distance_m = 0.0

    @property
    def clock_start(self) -> float:
        return self.pose.clock_start

    def start_clock(self, now: float | None = None) -> float:
        """Start the world's clock (once: a later call keeps the first start). Returns the start."""
        if not self.pose.clock_start:
            p = self.pose
            self.pose = Pose(p.x, p.y, p.theta, p.version + 1, time.time() if now is None else now)
        return self.pose.clock_start

    def world_time(self, now: float | None = None) -> float:
        """Seconds since the clock started (0 before), at Unix time `now` (default: now)."""
        if not self.pose.clock_start:
            return 0.0
        return max(0.0, (time.time() if now is None else now) - self.pose.clock_start)

    def touching(self, x: float, y: float, t: float = 0.0) -> Polygon | None:
        """What a robot at (x, y) would touch at world time `t`."""
        disc = Point(x, y).buffer(self.radius, quad_segs=16)
        hits = self._tree.query(disc, predicate="intersects")
        if len(hits):
            return self.solids[int(min(hits))]
        for obstacle in self.moving:
            shape = obstacle.shape_at(t)
            if shape.intersects(disc):
                return shape
        return None

    def move(self, x: float, y: float, theta: float, now: float | None = None) -> tuple[Pose, Polygon | None]:
        """Drive in a straight line towards (x, y); stop just before the first contact, with the
        moving obstacles where they are at the world time of `now` (default: now)."""
        if not all(math.isfinite(v) for v in (x, y, theta)):
            raise InvalidArgument("pose: x, y and theta must be finite")
        self.start_clock(now)
        world_time = self.world_time(now)
        start = self.pose
        length = math.hypot(x - start.x, y - start.y)
        if length > 5.0:
            raise InvalidArgument(f"pose: a move of {length:.2f} m is longer than the 5 m a bumper check covers")
        steps = max(1, math.ceil(length / CONTACT_STEP_M))
        reached = (start.x, start.y)
        contact: Polygon | None = None
        for i in range(1, steps + 1):
            t = i / steps
            px, py = start.x + t * (x - start.x), start.y + t * (y - start.y)
            contact = self.touching(px, py, world_time)
            if contact is not None:
                break
            reached = (px, py)
        self.distance_m += math.hypot(reached[0] - start.x, reached[1] - start.y)
        if contact is not None:
            self.collisions += 1
        self.pose = Pose(reached[0], reached[1], theta, start.version + 1, start.clock_start)
        return self.pose, contact

    def dock(self) -> bool:
        centre = Point(self.pose.x, self.pose.y)
        return any(s.shape.centroid.distance(centre) <= DOCK_REACH_M for s in self.scenario.charging_stations)


class WorldServer(Lifecycle):
    """SimulatedWorld over gRPC: start(), stop(), `async with`."""

    def __init__(self, scenario: Scenario, listen: str = "127.0.0.1:0", seed: int = 0) -> None:
        self.state = WorldState(scenario)
        self.seed = seed
        self._endpoint = Endpoint(
            listen,
            SERVICE_NAMES,
            lambda server: sim_pb2_grpc.add_SimulatedWorldServicer_to_server(_Servicer(self), server),
        )
        self._changed = asyncio.Condition()
        self._stopping = False

    @property
    def address(self) -> str:
        return self._endpoint.address

    async def start(self) -> None:
        await self._endpoint.start()
        log.info("sim world %r listening on %s", self.state.scenario.name, self.address)

    async def stop(self, grace: float = 1.0) -> None:
        if not self._endpoint.started or self._stopping:
            return
        self._stopping = True
        async with self._changed:
            self._changed.notify_all()
        await self._endpoint.stop(grace)

    async def moved(self) -> None:
        async with self._changed:
            self._changed.notify_all()

    async def ticks(self, period_s: float) -> AsyncIterator[float]:
        """Unix time now, then every `period_s` seconds (on the loop's clock, without drift) until
        the world stops."""
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        while not self._stopping:
            yield time.time()
            next_at += period_s
            async with self._changed:  # woken early only by the world stopping
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._changed.wait_for(lambda: self._stopping), next_at - loop.time())

    async def watch(self) -> AsyncIterator[Pose]:
        last = -1

        def changed() -> bool:
            return self.state.pose.version != last or self._stopping

        while not self._stopping:
            async with self._changed:
                await self._changed.wait_for(changed)
            if self._stopping:
                return
            pose = self.state.pose
            last = pose.version
            yield pose


def pose_to_pb(p: Pose) -> sim_pb2.RobotPose:
    return sim_pb2.RobotPose(x=p.x, y=p.y, theta=p.theta, version=p.version, clock_start_unix=p.clock_start)


class _Servicer(sim_pb2_grpc.SimulatedWorldServicer):
    def __init__(self, world: WorldServer) -> None:
        self._w = world

    @_grpc.servicer_method
    async def GetScene(self, request: sim_pb2.GetSceneRequest, context: aio.ServicerContext[Any, Any]) -> sim_pb2.Scene:
        return sim_pb2.Scene(scenario_yaml=self._w.state.scenario.source_text, seed=self._w.seed)

    @_grpc.servicer_method
    async def Move(self, request: sim_pb2.MoveRequest, context: aio.ServicerContext[Any, Any]) -> sim_pb2.MoveReply:
        now = time.time()
        pose, contact = self._w.state.move(request.pose.x, request.pose.y, request.pose.theta, now)
        await self._w.moved()
        reply = sim_pb2.MoveReply(
            pose=pose_to_pb(pose), collided=contact is not None, world_time_s=self._w.state.world_time(now)
        )
        if contact is not None:
            clipped = contact.intersection(box(*self._w.state.scenario.bounds))
            shape = clipped if isinstance(clipped, Polygon) and not clipped.is_empty else contact
            reply.contact.CopyFrom(
                polygon_to_pb(shapely.orient_polygons(shape) if hasattr(shapely, "orient_polygons") else shape)
            )
            log.info("robot touched an obstacle at (%.2f, %.2f)", pose.x, pose.y)
        return reply

    async def WatchRobot(
        self, request: sim_pb2.WatchRobotRequest, context: aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[sim_pb2.RobotPose]:
        async for pose in self._w.watch():
            yield pose_to_pb(pose)

    async def WatchScout(
        self, request: sim_pb2.WatchScoutRequest, context: aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[sim_pb2.ScoutPose]:
        try:
            scout = self._w.state.scenario.scout(request.scout_id)
        except ScenarioError as exc:
            await context.abort(grpc.StatusCode.NOT_FOUND, str(exc))
        rate = request.rate_hz or DEFAULT_SCOUT_RATE_HZ
        if not (math.isfinite(rate) and 0 < rate <= MAX_SCOUT_RATE_HZ):
            await context.abort(
                grpc.StatusCode.INVALID_ARGUMENT, f"rate_hz: {rate:g} is not in (0, {MAX_SCOUT_RATE_HZ:g}]"
            )
        async for now in self._w.ticks(1.0 / rate):
            world_time = self._w.state.world_time(now)
            pose = scout.pose_at(world_time)
            yield sim_pb2.ScoutPose(x=pose.x, y=pose.y, theta=pose.yaw, time_unix=now, world_time_s=world_time)

    @_grpc.servicer_method
    async def Start(self, request: sim_pb2.StartRequest, context: aio.ServicerContext[Any, Any]) -> sim_pb2.StartReply:
        started = self._w.state.clock_start
        clock_start = self._w.state.start_clock()
        if not started:
            log.info("world clock started: moving obstacles move")
            await self._w.moved()  # the cameras learn the clock's start from the pose stream
        return sim_pb2.StartReply(clock_start_unix=clock_start)

    @_grpc.servicer_method
    async def Dock(self, request: sim_pb2.DockRequest, context: aio.ServicerContext[Any, Any]) -> sim_pb2.DockReply:
        return sim_pb2.DockReply(docked=self._w.state.dock())


async def serve_world(scenario_path: str | None, listen: str, seed: int) -> int:
    stop = shutdown_event()
    world = WorldServer(load_scenario(scenario_path), listen, seed)
    await world.start()
    try:
        await stop.wait()
    finally:
        await world.stop()
    return 0


def fetch_scene(channel: grpc.Channel, world: str, timeout_s: float) -> tuple[Scenario, int]:
    """The scenario and seed a running world serves, waiting up to `timeout_s` for it to come up;
    Unavailable names the world when it does not answer."""
    try:
        scene = sim_pb2_grpc.SimulatedWorldStub(channel).GetScene(
            sim_pb2.GetSceneRequest(), timeout=timeout_s, wait_for_ready=True
        )
    except grpc.RpcError as exc:
        details = exc.details() if isinstance(exc, grpc.Call) else str(exc)
        raise Unavailable(f"simulated world {world} unreachable: {details}") from None
    return parse_scenario(scene.scenario_yaml, f"world {world}"), int(scene.seed)


def add_world_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default=None, help="scenario YAML (default: the built-in office)")
    p.add_argument("--listen", default="127.0.0.1:0", help="HOST:PORT (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--log-level", default=None)


def world_main(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    try:
        parse_address(args.listen, "--listen", allow_port_zero=True)
        return asyncio.run(serve_world(args.scenario, args.listen, args.seed))
    except DrvsError as exc:
        log.error("%s", exc)
        return 2
