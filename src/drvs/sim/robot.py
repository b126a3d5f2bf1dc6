"""The simulated robot: the paper's Algorithm 1 over DRVS, or its baseline without DRVS.

The robot knows the floor plan, its own pose (odometry) and which colours obstacles and charging
station markers have (or, with the `foreground` detector, nothing of the obstacles: anything on
the floor that is not the empty floor is one; and the ArUco ids of its own marker and its dock).
Everything else it learns from DRVS, or, in the baseline, by touching it.

By default it plans from fused delivery (`delivery="fused"`): single shots with
`snapshot()`, and while it drives `track()` snapshots of world objects along its way. A
track that stands still is an obstacle on its map; one that moves is predicted from its velocity
(drvs.sim.predict): the robot waits for it where it would cross its way, and ignores it once it
has gone. `delivery="per-camera"` is the paper's: every camera's reports, unioned.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import logging
import math
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import shapely
from shapely.geometry import LineString, Point, Polygon, box

from drvs.core.errors import DrvsError, ResourceExhausted
from drvs.core.model import Detection, PixelBox, Snapshot, WorldObject
from drvs.robot import DrvsClient, Subscription, Track
from drvs.sim.coverage import CoverageWatch
from drvs.sim.planner import NoPath, OccupancyGrid, plan_path
from drvs.sim.predict import STILL_MPS, MovingObstacle, TrackRecord, decide
from drvs.sim.scenario import Scenario
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire.convert import polygon_from_pb

if TYPE_CHECKING:
    from drvs.sim.robot_view import RobotView

log = logging.getLogger("drvs.sim.robot")

GRID_RESOLUTION_M = 0.1
#: Clearance kept beyond the robot's radius: detections are a few cm off, and cells are 10 cm.
SAFETY_MARGIN_M = 0.1
#: How far either side of the planned path the robot asks DRVS to look for obstacles.
LOOK_AHEAD_M = 1.5
TICK_S = 0.1
OBSTACLE_RATE_HZ = 2.0
SELF_RATE_HZ = 5.0
#: A green and a yellow marker this close together are a charging-station candidate.
STATION_PAIR_MAX_M = 0.5
#: Detections of obstacle colours this close to a station candidate's marker are the marker.
MARKER_MATCH_M = 0.25
#: A detection inside a known obstacle grown by this much is the same obstacle seen again (sensor
#: noise moves outlines by millimetres); it does not change the map or force a re-plan.
SAME_OBSTACLE_M = 0.05
#: Where no camera looks any more (a camera failed, went silent, or the server names parts of the
#: region nobody sees), the robot cannot know the way is clear: it creeps at this fraction of its
#: speed, as it would with its bumper as its only sensor, until a camera looks there again.
BLIND_SPEED_FRACTION = 0.25
#: Detectors the robot can find obstacles with: the paper's colours, or anything not empty floor.
DETECTORS = ("hsv", "foreground")
#: With `foreground` the robot sees itself: what lies within this much of the floor it has driven
#: over (its own disc, and where it stood, which a motion model shows for a while as changed floor)
#: is not an obstacle. A piece of a detection cut off by it that is smaller than SELF_SLIVER_M2 is
#: the edge of the robot's own blob, not an obstacle.
SELF_MARGIN_M = 0.1
SELF_SLIVER_M2 = 0.01
#: How the robot gets what cameras see: fused world objects (single shots and tracks) from the
#: server, or every camera's own reports (the paper's).
DELIVERIES = ("fused", "per-camera")
#: Snapshots a second of the obstacle tracks the robot follows while it drives.
TRACK_RATE_HZ = 2.0
#: A request refused for overload is asked again after the refusal's hint (this long without one),
#: for at most OVERLOAD_PATIENCE_S in all.
OVERLOAD_WAIT_S = 0.1
OVERLOAD_PATIENCE_S = 10.0
_T = TypeVar("_T")
#: A re-plan's new track request numbers its tracks anew, and a new track has no velocity until its
#: second look: a new track this close to where a moving track of an earlier request was last seen,
#: this recently, is that obstacle, and keeps its motion until the new track has its own.
HANDOVER_M = 0.5
HANDOVER_S = 1.5


class MissionFailed(Exception):
    pass


class SimRobot(CoverageWatch):
    def __init__(
        self,
        scenario: Scenario,
        world: sim_pb2_grpc.SimulatedWorldStub,
        drvs: DrvsClient | None,
        *,
        progress: Callable[[dict[str, Any]], None] = lambda p: None,
        max_time_s: float = 120.0,
        detector: str = "hsv",
        delivery: str = "fused",
        predict: bool = True,
    ) -> None:
        if detector not in DETECTORS:
            raise ValueError(f"detector {detector!r} is not one of {', '.join(DETECTORS)}")
        if delivery not in DELIVERIES:
            raise ValueError(f"delivery {delivery!r} is not one of {', '.join(DELIVERIES)}")
        self.scenario = scenario
        self.detector = detector
        self.delivery = delivery
        #: False: moving tracks are taken to stand where they were last seen (for comparison only).
        self.predict = predict
        #: Fused tracks: every track followed (key "request_id/track_id"), and those moving now.
        self.tracks: dict[str, TrackRecord] = {}
        self.moving: dict[str, MovingObstacle] = {}
        self.wait_steps = 0
        self.world_time_s = 0.0
        self._epoch = time.time()  # the world's clock start, once the robot sets off
        self._clock_started = False
        self.world = world
        self.drvs = drvs
        self.progress = progress
        self.max_time_s = max_time_s
        robot = scenario.robot
        self.inflate = robot.radius + SAFETY_MARGIN_M
        self.grid = OccupancyGrid(scenario.bounds, GRID_RESOLUTION_M)
        for wall in scenario.walls:
            self.grid.add_polygon(wall, self.inflate)
        self.pose = robot.start
        self.path_driven: list[tuple[float, float]] = [robot.start]
        self.plans: list[list[tuple[float, float]]] = []
        self.replans = 0
        self.collisions = 0
        #: Requests the server (or this robot's throttle) refused for overload, asked again later.
        self.overload_refusals = 0
        self.detections_used: list[Detection] = []
        self.known_obstacles: list[Polygon] = []
        self.contacts: list[Polygon] = []
        self.localisation_errors: list[float] = []
        self.heading_errors: list[float] = []
        #: (Unix time the move was sent, x, y, theta) of every pose: what a frame captured then shows.
        self.history: list[tuple[float, float, float, float]] = [(time.time(), *robot.start, 0.0)]
        self._swept: tuple[int, Polygon] | None = None
        self.ignore_near: list[tuple[float, float]] = []  # station markers: landmarks, not obstacles
        self._map_changed = False
        # Coverage: every camera's field of view as first listed, the areas no camera looks at now
        # (by the camera that stopped), and the continuous requests whose cameras are watched.
        self.fields_of_view: dict[str, Polygon] = {}
        self.blind: dict[str, Polygon] = {}
        #: Floor the latest answers said no camera sees (by source: see set_unseen).
        self.unseen: dict[str, Polygon] = {}
        self._blind_area: Polygon | None = None
        self._watching: list[tuple[Subscription, float]] = []
        self.coverage_events: list[dict[str, Any]] = []
        self.blind_steps = 0
        self._started = time.monotonic()
        self._last_progress = 0.0
        #: Where the robot shows itself in the live view (drvs.sim.robot_view), if anywhere.
        self.view: RobotView | None = None
        self.heading = 0.0
        # The paper's robot knows the obstacle colour model (yellow), not where obstacles are.
        self.obstacle_filters = sorted({o.color.filter_def for o in scenario.obstacles if o.color is not None})
        if detector == "foreground":
            self.obstacle_filters = ["foreground"]

    # --- map --------------------------------------------------------------------------------

    def mark(self, outline: Polygon, ragged: bool = False) -> bool:
        """The pessimistic union: every detection is occupied. True when the map changed.

        `ragged`: a foreground outline, traced on a noisy mask's edge: spikes of it that stick out of
        the known obstacles by less than SELF_SLIVER_M2 in all are that obstacle seen again."""
        if any(known.buffer(SAME_OBSTACLE_M).contains(outline) for known in self.known_obstacles):
            return False
        if ragged and self.known_obstacles:
            known = shapely.union_all([k.buffer(SAME_OBSTACLE_M) for k in self.known_obstacles])
            if outline.difference(known).area < SELF_SLIVER_M2:
                return False
        changed = self.grid.add_polygon(outline, self.inflate)
        if changed:
            self.known_obstacles.append(outline)
            self._map_changed = True
        return changed

    def forget(self, where: tuple[float, float]) -> None:
        """A track that started where a known obstacle lies turned out to move: that obstacle is not
        there any more. The map is rebuilt without it (no re-plan: the plan only gets freer)."""
        stay = [k for k in self.known_obstacles if not k.buffer(SAME_OBSTACLE_M).contains(Point(where))]
        if len(stay) == len(self.known_obstacles):
            return
        self.known_obstacles = stay
        self.grid = OccupancyGrid(self.scenario.bounds, GRID_RESOLUTION_M)
        for shape in [*self.scenario.walls, *stay, *self.contacts]:
            self.grid.add_polygon(shape, self.inflate)
        log.info("the obstacle seen at (%.2f, %.2f) moves: off the map", *where)

    # --- fused tracks -----------------------------------------------------------------------

    def use_snapshot(self, filter_def: str, request_id: str, snapshot: Snapshot) -> None:
        """One period of a fused track: standing tracks go on the map, moving ones are predicted."""
        for missing in snapshot.camera_errors.values():
            self.lose(missing.camera_id, f"{missing.code} {missing.message}")
        for camera_id in snapshot.camera_ids:
            self.regain(camera_id)
        alive: set[str] = set()
        for obj in snapshot.objects:
            if any(math.dist(obj.centroid_xy, p) < MARKER_MATCH_M for p in self.ignore_near):
                continue
            outline = obj.outline if not obj.outline.is_empty else box(*obj.bounds)
            if filter_def == "foreground":
                me = Point(self.pose).buffer(self.scenario.robot.radius + SELF_MARGIN_M)
                pieces = self.not_myself(outline)
                if outline.intersects(me) or not pieces:
                    continue  # the robot itself, or where it has been
                outline = max(pieces, key=lambda q: q.area)
            key = f"{request_id}/{obj.track_id}"
            alive.add(key)
            record = self.tracks.get(key)
            if record is None:
                record = self.tracks[key] = TrackRecord(key, filter_def, obj, snapshot.time)
                record.handed_over = self._moving_before(request_id, filter_def, obj, snapshot.time)
                if record.handed_over is not None:
                    record.moving = True
            else:
                was_moving = record.moving
                record.update(obj, snapshot.time)
                if record.moving and not was_moving:
                    self.forget(record.first_xy)
            if record.stands_still():
                record.static = True
                self.moving.pop(key, None)
                if self.mark(outline, ragged=filter_def == "foreground"):
                    self.detections_used.append(object_detection(filter_def, obj, outline))
            elif record.moving or not any(k.buffer(SAME_OBSTACLE_M).contains(outline) for k in self.known_obstacles):
                # Moving, or not yet known to stand still: predicted (velocity 0 until the tracker has
                # one, or the velocity of the moving track it takes over from, until it has its own).
                velocity = obj.velocity_xy
                if record.handed_over is not None and obj.speed_mps < STILL_MPS and record.snapshots <= 2:
                    velocity = record.handed_over.last.velocity_xy
                self.moving[key] = MovingObstacle.from_track(
                    key, dataclasses.replace(obj, outline=outline, velocity_xy=velocity), predict=self.predict
                )
        for key in [k for k in self.moving if k.startswith(request_id + "/") and k not in alive]:
            del self.moving[key]

    def _moving_before(self, request_id: str, filter_def: str, obj: WorldObject, at: float) -> TrackRecord | None:
        """The moving track of an earlier request that `obj`, new in `request_id`, continues: the
        same filter, last seen within HANDOVER_S and HANDOVER_M of it (the nearest), or None."""
        near = [
            r for r in self.tracks.values()
            if r.moving and not r.static and r.filter_def == filter_def and not r.key.startswith(request_id + "/")
            and at - r.last_seen <= HANDOVER_S and math.dist(r.last.centroid_xy, obj.centroid_xy) <= HANDOVER_M
        ]  # fmt: skip
        return min(near, key=lambda r: math.dist(r.last.centroid_xy, obj.centroid_xy), default=None)

    async def watch_tracks(self, region: Polygon) -> None:
        """Fused Algorithm 1: the server tracks the obstacles along the way while the robot drives."""
        drvs = self.drvs
        assert drvs is not None
        async with contextlib.AsyncExitStack() as stack:
            tracks = [
                await stack.enter_async_context(
                    await self.admitted(
                        functools.partial(drvs.track, f, region, rate_hz=TRACK_RATE_HZ, duration_s=self.max_time_s)
                    )
                )
                for f in self.obstacle_filters
            ]
            try:
                for track in tracks:
                    for missing in track.camera_errors.values():  # whom the server could not ask
                        self.lose(missing.camera_id, f"{missing.code} {missing.message}")
                self.set_unseen("watch", [p for t in tracks for p in t.uncovered])
                await asyncio.gather(*(self._follow(f, t) for f, t in zip(self.obstacle_filters, tracks, strict=True)))
            finally:
                self.set_unseen("watch", [])
                for track in tracks:
                    for key in [k for k in self.moving if k.startswith(track.request_id + "/")]:
                        del self.moving[key]

    async def _follow(self, filter_def: str, track: Track) -> None:
        try:
            async for snapshot in track:
                self.use_snapshot(filter_def, track.request_id, snapshot)
        except DrvsError as exc:  # the stream broke (server gone ...): nobody looks for us any more
            for camera_id in track.camera_ids:
                self.lose(camera_id, f"track {track.request_id} ended: {exc}")

    def use_detections(self, detections: Sequence[Detection]) -> None:
        for d in detections:
            if any(d.centroid.distance(Point(p)) < MARKER_MATCH_M for p in self.ignore_near):
                continue
            if d.filter_def == "foreground":
                if any([self.mark(piece, ragged=True) for piece in self.not_myself(d.outline)]):
                    self.detections_used.append(d)
            elif self.mark(d.outline):
                self.detections_used.append(d)

    def swept(self) -> Polygon:
        """The floor the robot has covered on its way so far, grown by SELF_MARGIN_M."""
        if self._swept is None or self._swept[0] != len(self.path_driven):
            line = LineString(self.path_driven) if len(self.path_driven) > 1 else Point(self.path_driven[0])
            area = line.buffer(self.scenario.robot.radius + SELF_MARGIN_M, quad_segs=8)
            shapely.prepare(area)
            self._swept = (len(self.path_driven), area)
        return self._swept[1]

    def not_myself(self, outline: Polygon) -> list[Polygon]:
        """A foreground outline without the robot: the parts off the floor it has driven over.
        Nothing the robot could hit can lie where it has been (the world's obstacles stand still)."""
        swept = self.swept()
        if not swept.intersects(outline):
            return [outline]
        rest = outline.difference(swept)
        return [p for p in getattr(rest, "geoms", [rest]) if isinstance(p, Polygon) and p.area >= SELF_SLIVER_M2]

    def corridor(self, path: Sequence[tuple[float, float]]) -> Polygon:
        line = LineString(path) if len(path) > 1 else Point(path[0])
        region = line.buffer(LOOK_AHEAD_M).intersection(box(*self.scenario.bounds))
        return region if isinstance(region, Polygon) else region.convex_hull

    # --- DRVS (coverage: drvs.sim.coverage) ---------------------------------------------------

    async def admitted(self, ask: Callable[[], Awaitable[_T]]) -> _T:
        """`ask()`, asked again after a refusal for overload (RESOURCE_EXHAUSTED: the server's door,
        or this robot's own throttle), after the wait the refusal hints at: the robot goes on
        with what it knows meanwhile, as it does where a camera is missing. A server that refuses
        for OVERLOAD_PATIENCE_S ends the mission."""
        waited = 0.0
        while True:
            try:
                return await ask()
            except ResourceExhausted as exc:
                if waited >= OVERLOAD_PATIENCE_S:
                    raise
                wait = exc.retry_after_s or OVERLOAD_WAIT_S
                self.overload_refusals += 1
                log.info("overloaded: %s; asking again in %.0f ms", exc, wait * 1000)
                await asyncio.sleep(wait)
                waited += wait

    async def look(self, filters: Sequence[str], region: Polygon) -> list[Detection]:
        assert self.drvs is not None
        if self.delivery == "fused":
            return await self.look_fused(filters, region)
        drvs = self.drvs
        results = await asyncio.gather(
            *(self.admitted(functools.partial(drvs.detect, f, region, timeout_s=5.0)) for f in filters)
        )
        found: list[Detection] = []
        for result in results:
            self.check_coverage(result)
            found.extend(result.detections)
        self.set_unseen("look", [p for r in results for p in r.uncovered])
        return found

    async def _fused_shot(self, filter_def: str, region: Polygon) -> Snapshot:
        assert self.drvs is not None
        return await self.drvs.snapshot(filter_def, region, timeout_s=5.0)

    async def look_fused(self, filters: Sequence[str], region: Polygon) -> list[Detection]:
        """One fused single shot per filter: each physical object once, whatever camera saw it."""
        snapshots = await asyncio.gather(
            *(self.admitted(functools.partial(self._fused_shot, f, region)) for f in filters)
        )
        found: list[Detection] = []
        for f, snapshot in zip(filters, snapshots, strict=True):
            for missing in snapshot.camera_errors.values():
                self.lose(missing.camera_id, f"{missing.code} {missing.message}")
            for camera_id in snapshot.camera_ids:
                self.regain(camera_id)
            found.extend(object_detection(f, o) for o in snapshot.objects)
        self.set_unseen("look", [p for s in snapshots for p in s.uncovered])
        return found

    async def watch_obstacles(self, region: Polygon) -> None:
        """Algorithm 1's callback: obstacles stream in while the robot drives."""
        assert self.drvs is not None
        drvs = self.drvs
        subs = [
            await self.admitted(
                functools.partial(drvs.subscribe, f, region, rate_hz=OBSTACLE_RATE_HZ, duration_s=self.max_time_s)
            )
            for f in self.obstacle_filters
        ]
        now = asyncio.get_running_loop().time()
        watched = [(s, now) for s in subs]
        self._watching.extend(watched)
        try:
            for sub in subs:
                self.check_coverage(sub.result, running=True)  # whom the server could not ask
            self.set_unseen("watch", [p for s in subs for p in s.result.uncovered])
            await asyncio.gather(*(self._consume(s) for s in subs))
        finally:
            self.set_unseen("watch", [])
            for item in watched:
                self._watching.remove(item)
            for s in subs:
                s.close()

    async def _consume(self, sub: Subscription) -> None:
        async for report in sub:
            if report.error:
                self.lose(report.camera_id, f"{report.error_code} {report.error}")
            else:
                self.regain(report.camera_id)
            self.use_detections(report.detections)

    @property
    def self_filter(self) -> str:
        """What finds the robot: its ArUco marker (position and heading), else its colour."""
        marker = self.scenario.robot.marker
        return marker.filter_def if marker is not None else self.scenario.robot.color.filter_def

    async def watch_self(self) -> None:
        """Localise: the cameras that see the robot's own marker report where it is."""
        assert self.drvs is not None
        drvs = self.drvs
        sub = await self.admitted(
            lambda: drvs.subscribe(
                self.self_filter, box(*self.scenario.bounds), rate_hz=SELF_RATE_HZ, duration_s=self.max_time_s
            )
        )
        try:
            async for report in sub:
                if not report.detections:
                    continue
                if self.scenario.robot.marker is not None:
                    self.fix_by_marker(report.detections)
                else:
                    near = min(report.detections, key=lambda d: d.centroid.distance(Point(self.pose)))
                    self.localisation_errors.append(near.centroid.distance(Point(self.pose)))
        finally:
            sub.close()

    def fix_by_marker(self, detections: Sequence[Detection]) -> None:
        """A fix from the robot's own ArUco marker (its id is unique in the building), against the
        pose the frame shows: the last one sent before the frame's capture time, or the one before
        it if the frame was rendered while that move was in flight (whichever is nearer)."""
        for d in detections:
            t = d.capture_time
            before = [h for h in self.history if h[0] <= t][-2:] or self.history[:1]
            best = min(before, key=lambda h: math.dist(d.centroid_xy, h[1:3]))
            self.localisation_errors.append(math.dist(d.centroid_xy, best[1:3]))
            if d.heading_deg is not None:
                error = (d.heading_deg - math.degrees(best[3]) + 180.0) % 360.0 - 180.0
                self.heading_errors.append(abs(error))

    # --- driving ----------------------------------------------------------------------------

    def plan(self, goal: tuple[float, float]) -> list[tuple[float, float]]:
        path = plan_path(self.grid, self.pose, goal)
        self.plans.append(path)
        if self.view is not None:
            self.view.update(self.pose, self.heading, path)
        return path

    async def go_to(self, goal: tuple[float, float], *, look: bool) -> bool:
        """Drive to goal, re-planning whenever the map changes; False if it cannot be reached."""
        try:
            path = self.plan(goal)
        except NoPath:
            return False
        watcher: asyncio.Task[None] | None = None
        if look and self.drvs is not None:
            for _ in range(3):  # look along the plan until the plan stops changing
                self._map_changed = False
                self.use_detections(await self.look(self.obstacle_filters, self.corridor(path)))
                if not self._map_changed:
                    break
                path = self.plan(goal)
                self.replans += 1
            self._map_changed = False
        if not self._clock_started:  # the robot sets off: the world's clock starts, obstacles move
            self._epoch = (await self.world.Start(sim_pb2.StartRequest(), timeout=10)).clock_start_unix
            self._clock_started = True
        try:
            while True:
                if watcher is not None and watcher.done() and not watcher.cancelled():
                    if watcher.exception() is not None:
                        log.warning("watching obstacles failed: %s", watcher.exception())
                    watcher = None  # look again (a track ended early, e.g. a server restart)
                if look and self.drvs is not None and watcher is None:
                    watch = self.watch_tracks if self.delivery == "fused" else self.watch_obstacles
                    watcher = asyncio.get_running_loop().create_task(watch(self.corridor(path)))
                if self._map_changed:
                    self._map_changed = False
                    try:
                        path = self.plan(goal)
                    except NoPath:
                        return False
                    self.replans += 1
                    if watcher is not None:  # look along the new plan
                        watcher.cancel()
                        with contextlib.suppress(asyncio.CancelledError):
                            await watcher
                        watcher = None
                    continue
                if math.dist(self.pose, goal) < 0.05 or len(path) < 2:
                    return math.dist(self.pose, goal) < 0.3
                if time.monotonic() - self._started > self.max_time_s:
                    raise MissionFailed(f"out of time after {self.max_time_s:g} s")
                await self.step_towards(path)
        finally:
            if watcher is not None:
                watcher.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await watcher

    async def step_towards(self, path: list[tuple[float, float]]) -> None:
        target = path[1]
        distance = math.dist(self.pose, target)
        speed = self.scenario.robot.speed_mps
        self.check_silence()
        blind = self.blind_area()
        if blind is not None and blind.intersects(Point(self.pose).buffer(self.inflate + speed * TICK_S)):
            speed *= BLIND_SPEED_FRACTION  # about to drive where nobody looks
            self.blind_steps += 1
        step = min(speed * TICK_S, distance)
        if self.moving and not decide(path, step, speed, list(self.moving.values()), time.time(), self.inflate):
            step = 0.0  # let the moving obstacle pass: wait here (the world's clock and cameras go on)
            self.wait_steps += 1
        x = self.pose[0] + (target[0] - self.pose[0]) * step / distance if distance else target[0]
        y = self.pose[1] + (target[1] - self.pose[1]) * step / distance if distance else target[1]
        heading = math.atan2(target[1] - self.pose[1], target[0] - self.pose[0])
        tick = asyncio.get_running_loop().create_task(asyncio.sleep(TICK_S))
        sent = time.time()
        reply = await self.world.Move(sim_pb2.MoveRequest(pose=sim_pb2.RobotPose(x=x, y=y, theta=heading)))
        self.pose = (reply.pose.x, reply.pose.y)
        self.world_time_s = reply.world_time_s
        self.history.append((sent, reply.pose.x, reply.pose.y, reply.pose.theta))
        self.path_driven.append(self.pose)
        self.heading = reply.pose.theta
        if reply.collided:
            self.collisions += 1
            contact = polygon_from_pb(reply.contact, "contact")
            self.contacts.append(contact)
            log.info("collision at (%.2f, %.2f)", *self.pose)
            self.mark(contact)
        elif math.dist(self.pose, target) < 1e-6 and step > 0:
            path.pop(0)
        path[0] = self.pose
        if self.view is not None:
            self.view.update(self.pose, self.heading, path)
        self.report_progress()
        await tick  # drive in real time, so the cameras see the robot move

    def report_progress(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_progress >= 0.25:
            self._last_progress = now
            self.progress(
                {
                    "t": round(now - self._started, 2),
                    "x": round(self.pose[0], 3),
                    "y": round(self.pose[1], 3),
                    "replans": self.replans,
                    "collisions": self.collisions,
                    "detections": len(self.detections_used),
                }
            )

    # --- missions ---------------------------------------------------------------------------

    async def navigate(self) -> dict[str, Any]:
        goal = self.scenario.robot.goal
        assert goal is not None
        localiser = None
        if self.drvs is not None:
            await self.learn_cameras()
            localiser = asyncio.get_running_loop().create_task(self.watch_self())
        try:
            reached = await self.go_to(goal, look=self.drvs is not None)
        finally:
            if localiser is not None:
                localiser.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await localiser
        return {"reached_goal": reached, "charging_station": None, "candidates": []}

    async def dock_markers(self, docks: Sequence[str]) -> tuple[list[tuple[float, float]], list[Detection]]:
        """Docks marked by an ArUco id: where each dock's marker lies is a station. The marker lies
        flat (no obstacle), and its id tells it from every other marker on the floor."""
        found = await self.look(docks, box(*self.scenario.bounds))
        self.ignore_near.extend((d.centroid.x, d.centroid.y) for d in found)
        return [(d.centroid.x, d.centroid.y) for d in found], found

    async def colour_stations(self) -> tuple[list[tuple[float, float]], list[Detection]]:
        """The paper's stations: a green and a yellow marker close together."""
        colors = self.scenario.colors
        green, yellow = colors["green"].filter_def, colors["yellow"].filter_def
        greens = await self.look([green], box(*self.scenario.bounds))
        candidates: list[tuple[float, float]] = []
        used: list[Detection] = []
        for g in greens:
            gx, gy = g.centroid.x, g.centroid.y
            yellows = await self.look([yellow], box(gx - 0.5, gy - 0.5, gx + 0.5, gy + 0.5))
            for y in yellows:
                if g.centroid.distance(y.centroid) <= STATION_PAIR_MAX_M:
                    candidates.append(((gx + y.centroid.x) / 2, (gy + y.centroid.y) / 2))
                    used.extend([g, y])
                    self.ignore_near.extend([(gx, gy), (y.centroid.x, y.centroid.y)])
        log.info("%d green marker(s)", len(greens))
        return candidates, used

    async def find_charging_station(self) -> dict[str, Any]:
        if self.drvs is None:
            raise MissionFailed("find_charging_station needs DRVS: the markers are only seen by cameras")
        await self.learn_cameras()
        stations = self.scenario.charging_stations
        docks = sorted({o.aruco.filter_def for o in stations if o.aruco is not None})
        candidates: list[tuple[float, float]] = []
        used: list[Detection] = []
        if docks:
            candidates, used = await self.dock_markers(docks)
        if any(o.aruco is None for o in stations):  # the paper's: between a green and a yellow marker
            paired, pair_used = await self.colour_stations()
            candidates += paired
            used += pair_used
        self.detections_used.extend(used)
        candidates.sort(key=lambda c: math.dist(c, self.pose))
        log.info("%d station candidate(s)", len(candidates))
        for candidate in candidates:
            if not await self.go_to(candidate, look=True):
                continue
            docked = await self.world.Dock(sim_pb2.DockRequest())
            if docked.docked:
                return {
                    "reached_goal": True,
                    "charging_station": [round(candidate[0], 4), round(candidate[1], 4)],
                    "candidates": [[round(c[0], 4), round(c[1], 4)] for c in candidates],
                }
        return {
            "reached_goal": False,
            "charging_station": None,
            "candidates": [[round(c[0], 4), round(c[1], 4)] for c in candidates],
        }


def object_detection(filter_def: str, obj: WorldObject, outline: Polygon | None = None) -> Detection:
    """A fused world object as the detection the robot's map and result.json take: its cameras
    joined by "," as camera_id, its newest capture time."""
    shape = outline if outline is not None else obj.outline
    return Detection(
        outline=shape,
        bounds=shape.bounds if not shape.is_empty else obj.bounds,
        centroid_xy=obj.centroid_xy,
        ground_contact_xy=obj.centroid_xy,
        pixel_box=PixelBox(0, 0, 0, 0),
        area_m2=obj.area_m2,
        area_px=0.0,
        score=obj.score,
        filter_def=filter_def,
        camera_id=",".join(obj.camera_ids),
        capture_time=obj.last_seen,
        marker_id=obj.marker_id,
        heading_deg=obj.marker_heading_deg,
        label=obj.label,
    )
