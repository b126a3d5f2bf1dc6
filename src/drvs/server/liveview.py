"""What a server shows live (`drvs-server --foxglove HOST:PORT`) and records (`--record FILE.mcap`).

The server's request path only hands messages over (`request`, `reply`, `report`: a copy of the
bytes, without secrets, onto a queue), and only those that passed its checks: a refused request
or a rejected report is neither shown nor recorded. Each must also pass the hub's `admit` (at most
drvs.live.liveview.MAX_MESSAGE_BYTES, within its bytes a second), and the queue holds at most
`MAX_BACKLOG_BYTES`; what does not fit is dropped and counted. One thread of its own logs them and
draws the scene from them, so a slow viewer or a large scene never holds a robot's request up. The
registry is read on the event loop (it is not thread-safe) five times a second, and only what changed is sent on; every
`REFRESH_S` the whole scene again, for viewers that joined late and for a recording's readers who
seek into the middle of it.

Topics (docs/operations.md, "Live view and recordings"):

  /drvs/floor_plan        foxglove.SceneUpdate    walls, desks, the floor's bounds (--floor-plan)
  /drvs/cameras           foxglove.SceneUpdate    each registered camera's field of view
  /drvs/requests          foxglove.SceneUpdate    each active request's region
  /drvs/detections        foxglove.SceneUpdate    the detections cameras report to the server
  /drvs/tracks            foxglove.SceneUpdate    fused world objects, as delivered to robots
  /drvs/rpc/cameras       drvs.v1.ListCamerasReply  the registry, whenever it changes
  /drvs/rpc/requests      drvs.v1.DetectionRequest  every request the server took (secrets cleared)
  /drvs/rpc/replies       drvs.v1.DetectionReply    every reply the server sends a robot
  /drvs/rpc/reports       drvs.v1.DetectionReport   every report the server accepted (keys cleared)

and what robots publish into the view (the office robot: /robot/pose, /robot/paths), each client on
channels of its own, never under /drvs/ (drvs.live.liveview).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from shapely.geometry import Polygon, box

from drvs.core._files import read_yaml
from drvs.core.errors import InvalidArgument
from drvs.live import liveview as lv
from drvs.server.registry import CameraEntry, Registry
from drvs.v1 import detection_pb2, registry_pb2
from drvs.wire.convert import detection_from_pb, region_from_pb, snapshot_from_pb

log = logging.getLogger("drvs.server.liveview")


class Observed(Protocol):
    """What the live view reads of the server (DrvsServer is one): its cameras, as it lists them."""

    @property
    def registry(self) -> Registry: ...

    def camera_info(self, e: CameraEntry) -> registry_pb2.CameraInfo:
        """A camera as ListCameras describes it."""
        ...


#: How often the registry is read for cameras that came, went or moved.
CAMERA_POLL_S = 0.2
#: How often the whole scene is sent again (floor plan, every camera).
REFRESH_S = 2.0
#: How long a single shot's region and a report's detections stay drawn.
SHORT_LIFETIME_S = 1.0
#: A track stays drawn this long after its last snapshot (snapshots refresh it).
TRACK_LIFETIME_S = 1.0
#: Bytes of messages waiting for the view's thread beyond this are dropped (and counted), never queued.
MAX_BACKLOG_BYTES = 64 << 20


@dataclass(frozen=True)
class FloorPlan:
    bounds: tuple[float, float, float, float] | None
    walls: tuple[Polygon, ...]


def load_floor_plan(path: Path) -> FloorPlan:
    """A floor plan from YAML or JSON: a scenario file (its `floor_plan`) or a file whose top level
    has `bounds: [xmin, ymin, xmax, ymax]` and `walls: [[[x, y], ...], ...]` (metres, map frame)."""
    data = read_yaml(path, "--floor-plan")
    if isinstance(data, dict) and isinstance(data.get("floor_plan"), dict):
        data = data["floor_plan"]
    if not isinstance(data, dict) or "walls" not in data:
        raise InvalidArgument(f"--floor-plan {path}: expected `walls:` (a list of polygons), or a scenario file")
    walls: list[Polygon] = []
    for i, raw in enumerate(data["walls"] or []):
        try:
            points = [(float(x), float(y)) for x, y in raw]
        except (TypeError, ValueError):
            raise InvalidArgument(f"--floor-plan {path}: walls[{i}]: not a list of [x, y] points") from None
        polygon = Polygon(points) if len(points) >= 3 else Polygon()
        if not polygon.is_valid or polygon.area <= 0:
            raise InvalidArgument(f"--floor-plan {path}: walls[{i}]: not a simple polygon with an area")
        walls.append(polygon)
    bounds = data.get("bounds")
    if bounds is not None:
        try:
            x0, y0, x1, y1 = (float(v) for v in bounds)
        except (TypeError, ValueError):
            raise InvalidArgument(f"--floor-plan {path}: bounds: expected [xmin, ymin, xmax, ymax]") from None
        if not (x0 < x1 and y0 < y1):
            raise InvalidArgument(f"--floor-plan {path}: bounds: expected [xmin, ymin, xmax, ymax]")
        bounds = (x0, y0, x1, y1)
    return FloorPlan(bounds, tuple(walls))


class ServerView:
    """The server's live view and recording, on `hub`. `start()` on the server's event loop."""

    def __init__(self, hub: lv.LiveHub, server: Observed, floor_plan: FloorPlan | None = None) -> None:
        self.hub = hub
        self.server = server
        self.floor_plan = floor_plan
        self._dropped = 0  # by the view itself (too large to copy, its queue full); the hub counts its own
        self._queue: queue.SimpleQueue[tuple[str, Any, float, int] | None] = queue.SimpleQueue()
        self._backlog = 0
        self._thread = threading.Thread(target=self._run, name="drvs-liveview", daemon=True)
        self._poller: asyncio.Task[None] | None = None
        # camera id -> what was last drawn of it (a change redraws it)
        self._drawn: dict[str, tuple[Any, ...]] = {}
        self._last_refresh = 0.0
        # Drawn once, sent again at each refresh: the floor plan, and each camera as last drawn.
        self._floor_msg: Any = None
        self._camera_entities: dict[str, tuple[tuple[Any, ...], Any]] = {}
        scene = hub.scene_channel
        self.floor = scene("/drvs/floor_plan")
        self.cameras = scene("/drvs/cameras")
        self.requests = scene("/drvs/requests")
        self.detections = scene("/drvs/detections")
        self.tracks = scene("/drvs/tracks")
        self.rpc_cameras = hub.proto_channel("/drvs/rpc/cameras", registry_pb2.ListCamerasReply)
        self.rpc_requests = hub.proto_channel("/drvs/rpc/requests", detection_pb2.DetectionRequest)
        self.rpc_replies = hub.proto_channel("/drvs/rpc/replies", detection_pb2.DetectionReply)
        self.rpc_reports = hub.proto_channel("/drvs/rpc/reports", detection_pb2.DetectionReport)

    @classmethod
    def open(
        cls,
        server: Observed,
        listen: tuple[str, int] | None,
        record: Path | None,
        floor_plan: Path | None,
        *,
        token: str | None = None,
        bytes_per_s: float | None = None,
    ) -> ServerView:
        """The view DrvsServer.show describes (its hub: clientPublish on, `token` and `bytes_per_s`)."""
        lv.require("--foxglove" if listen is not None else "--record")
        plan = load_floor_plan(floor_plan) if floor_plan is not None else None
        hub = lv.LiveHub(
            "drvs-server",
            listen=listen,
            record=record,
            accept_clients=True,
            token=token,
            bytes_per_s=bytes_per_s or lv.BYTES_PER_S,
        )
        return cls(hub, server, plan)

    # --- from the server's event loop --------------------------------------------------------

    def start(self) -> None:
        self._thread.start()
        self._poller = asyncio.get_running_loop().create_task(self._poll())

    async def stop(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._poller
            with contextlib.suppress(Exception):  # the registry as it was at the end, even if it changed just now
                self._cameras_now()
        self._queue.put(None)
        await asyncio.to_thread(self._thread.join, 10)
        self.hub.close()

    @property
    def dropped(self) -> int:
        """Messages neither shown nor recorded: too large, beyond the hub's rate, or its queue full."""
        return self._dropped + self.hub.dropped

    def _put(self, kind: str, item: Any, nbytes: int) -> None:
        if self._backlog + nbytes > MAX_BACKLOG_BYTES:
            self._dropped += 1
            return
        self._backlog += nbytes
        self._queue.put((kind, item, time.time(), nbytes))

    def _admit(self, message: Any) -> bool:
        return bool(self.hub.admit(message.ByteSize()))

    def copy(self, message: detection_pb2.DetectionRequest) -> bytes | None:
        """A robot's request as it came in, before the server looks at it (answering may change the
        message), without its report secret and key; None when it is too large to show. Hand it
        to `request` once the server took the request."""
        if message.ByteSize() > lv.MAX_MESSAGE_BYTES:
            return None
        if message.report_secret or message.report_key:
            copy = detection_pb2.DetectionRequest()
            copy.CopyFrom(message)
            copy.ClearField("report_secret")
            copy.ClearField("report_key")
            message = copy
        return message.SerializeToString()

    def request(self, data: bytes | None) -> None:
        """A robot's request the server took, as `copy` made it."""
        if data is None:
            self._dropped += 1
            return
        if not self.hub.admit(len(data)):
            return
        self._put("request", data, len(data))

    def reply(self, message: detection_pb2.DetectionReply) -> None:
        if self._admit(message):
            data = message.SerializeToString()
            self._put("reply", data, len(data))

    def report(self, message: detection_pb2.DetectionReport) -> None:
        """A camera's report the server accepted; its report key is not recorded."""
        if not self._admit(message):
            return
        data = message.SerializeToString()
        if message.report_key:
            copy = detection_pb2.DetectionReport()
            copy.ParseFromString(data)
            copy.ClearField("report_key")
            data = copy.SerializeToString()
        self._put("report", data, len(data))

    async def _poll(self) -> None:
        while True:
            try:
                self._cameras_now()
            except Exception:  # the view must never take the server down
                log.exception("live view: reading the registry failed")
            await asyncio.sleep(CAMERA_POLL_S)

    def _cameras_now(self) -> None:
        registry = self.server.registry
        now: dict[str, tuple[Any, ...]] = {}
        for e in registry.cameras():
            fov = e.field_of_view
            key = (e.address, fov.bounds if not fov.is_empty else None, fov.area, registry.unroutable(e.camera_id))
            now[e.camera_id] = key
        refresh = time.monotonic() - self._last_refresh >= REFRESH_S
        if now == self._drawn and not refresh:
            return
        if refresh:
            self._last_refresh = time.monotonic()
        changed = [registry.get(i) for i, k in now.items() if refresh or self._drawn.get(i) != k]
        gone = [i for i in self._drawn if i not in now]
        cameras = [(e.camera_id, e.field_of_view, e.mobile, now[e.camera_id]) for e in changed]
        infos = None
        if now != self._drawn:
            infos = registry_pb2.ListCamerasReply(
                cameras=[self.server.camera_info(registry.get(i)) for i in sorted(now)]
            ).SerializeToString()
        self._drawn = now
        self._put("cameras", (cameras, gone, infos, refresh), 1024 * len(cameras) + len(infos or b""))

    # --- the view's own thread ----------------------------------------------------------------

    def _run(self) -> None:
        self._draw_floor()
        while True:
            item = self._queue.get()
            if item is None:
                return
            kind, payload, t, nbytes = item
            self._backlog -= nbytes
            try:
                getattr(self, f"_on_{kind}")(payload, t)
            except Exception:
                log.exception("live view: drawing a %s failed", kind)

    def _draw_floor(self) -> None:
        plan = self.floor_plan
        if plan is None:
            return
        if self._floor_msg is None:
            entities = [lv.wall_entity(f"wall/{i}", w) for i, w in enumerate(plan.walls)]
            if plan.bounds is not None:
                entities.append(
                    lv.area_entity(
                        "floor", box(*plan.bounds), lv.rgba(0.93, 0.93, 0.9, 0.35), edge=lv.rgba(0.3, 0.3, 0.3)
                    )
                )
            self._floor_msg = lv.scene(entities)
        self.floor.log(self._floor_msg)

    def _on_cameras(self, payload: Any, t: float) -> None:
        cameras, gone, infos, refresh = payload
        if refresh:
            self._draw_floor()
        entities = []
        for camera_id, fov, mobile, key in cameras:
            if fov.is_empty:
                continue
            cached = self._camera_entities.get(camera_id)
            if cached is None or cached[0] != key:
                color = lv.rgba(0.6, 0.6, 0.6, 0.12) if key[3] else lv.palette(camera_id, 0.15)
                entity = lv.area_entity(
                    f"camera/{camera_id}",
                    fov,
                    color,
                    edge=lv.palette(camera_id),
                    label=camera_id + (" (mobile)" if mobile else ""),
                    t=t,
                    metadata={"camera_id": camera_id, "mobile": str(mobile).lower()},
                )
                cached = self._camera_entities[camera_id] = (key, entity)
            entities.append(cached[1])
        for camera_id in gone:
            self._camera_entities.pop(camera_id, None)
        deletions = [lv.deletion(f"camera/{i}") for i in gone]
        deletions += [lv.deletion(f"camera/{c[0]}") for c in cameras if c[1].is_empty]
        if entities or deletions:
            self.cameras.log(lv.scene(entities, deletions), log_time=_ns(t))
        if infos is not None:
            self.rpc_cameras.log(infos, log_time=_ns(t))

    def _on_request(self, data: bytes, t: float) -> None:
        self.rpc_requests.log(data, log_time=_ns(t))
        message = detection_pb2.DetectionRequest.FromString(data)
        entity = f"request/{message.request_id}"
        if message.cancel:
            self.requests.log(lv.scene(deletions=[lv.deletion(entity)]), log_time=_ns(t))
            return
        if not message.HasField("region"):
            return
        try:
            region = region_from_pb(message.region)
        except Exception:
            return  # the server refuses it and says why; nothing to draw
        duration = message.continuous.duration_s if message.HasField("continuous") else 0.0
        self.requests.log(
            lv.scene(
                [
                    lv.area_entity(
                        entity,
                        region,
                        lv.rgba(0.2, 0.5, 1.0, 0.08),
                        edge=lv.rgba(0.2, 0.45, 1.0, 0.9),
                        label=f"{message.robot_id or 'robot'}: {message.filter_def}",
                        z=0.03,
                        lifetime_s=max(duration, SHORT_LIFETIME_S),
                        t=t,
                        metadata={"request_id": message.request_id, "filter_def": message.filter_def},
                    )
                ]
            ),
            log_time=_ns(t),
        )

    def _on_reply(self, data: bytes, t: float) -> None:
        self.rpc_replies.log(data, log_time=_ns(t))
        message = detection_pb2.DetectionReply.FromString(data)
        if not message.HasField("snapshot"):
            return
        entities = []
        for o in snapshot_from_pb(message.snapshot).objects:
            key = f"{message.request_id}/{o.track_id}"
            geometry = _drawn(o.outline, o.bounds)
            name = o.label or (f"marker {o.marker_id}" if o.marker_id is not None else "object")
            speed = o.speed_mps
            label = f"#{o.track_id} {name}" + (f" {speed:.2f} m/s" if speed > 0.05 else "")
            entities.append(
                lv.area_entity(
                    f"track/{key}",
                    geometry,
                    lv.palette(key, 0.45),
                    edge=lv.palette(key),
                    label=label,
                    z=0.05,
                    lifetime_s=TRACK_LIFETIME_S,
                    t=t,
                    metadata={
                        "request_id": message.request_id,
                        "track_id": str(o.track_id),
                        "cameras": ",".join(o.camera_ids),
                    },
                )
            )
        if entities:
            self.tracks.log(lv.scene(entities), log_time=_ns(t))

    def _on_report(self, data: bytes, t: float) -> None:
        self.rpc_reports.log(data, log_time=_ns(t))
        message = detection_pb2.DetectionReport.FromString(data)
        entities = []
        for i, pb in enumerate(message.detections):
            d = detection_from_pb(pb, message.camera_id, 0.0, "")
            geometry = _drawn(d.outline, d.bounds)
            entities.append(
                lv.area_entity(
                    f"detection/{message.camera_id}/{message.request_id}/{i}",
                    geometry,
                    lv.palette(message.camera_id, 0.3),
                    edge=lv.palette(message.camera_id),
                    z=0.04,
                    lifetime_s=SHORT_LIFETIME_S,
                    t=t,
                    metadata={"camera_id": message.camera_id, "request_id": message.request_id},
                    filled=False,
                )
            )
        if entities:
            self.detections.log(lv.scene(entities), log_time=_ns(t))


def _drawn(outline: Polygon, bounds: tuple[float, float, float, float]) -> Polygon:
    """What to draw of an outline the wire carried: itself, repaired if it is not a valid area (as
    a packed ring may be), or its bounds when it is empty (outlines omitted) or nothing is left."""
    if not outline.is_empty and not (outline.is_valid and outline.area > 0):
        outline = outline.buffer(0)
    return outline if not outline.is_empty else box(*bounds)


def _ns(t: float) -> int:
    return int(t * 1e9)
