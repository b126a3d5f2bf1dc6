"""The bridge: a fused DRVS track, followed with the robot's client (DrvsClient.track), published on
ROS 2 topics through Cyclone DDS (drvs.ros2.dds), snapshot by snapshot; /drvs/region changes the
region while it runs, /clock gives the stamps under --use-sim-time.

A track runs for at most MAX_DURATION_S (an hour); the bridge opens the next when one ends, and a
new one when the region changes, so it runs until it is stopped. Track ids start anew with each
track (the markers of the ended ones are deleted).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cyclonedds.core import Listener
from shapely.geometry import Polygon

from drvs.core.errors import InvalidArgument, Unavailable
from drvs.core.model import MAX_DURATION_S, Snapshot
from drvs.robot.client import DrvsClient
from drvs.robot.snapshots import snapshot_json
from drvs.ros2.cdr import snapshot_payloads
from drvs.ros2.convert import (
    CLOCK_TOPIC,
    REGION_TYPE,
    MarkerState,
    Style,
    output_topics,
    region_from_msg,
)
from drvs.ros2.dds import Node, write_cdr

log = logging.getLogger("drvs.ros2")

#: /diagnostics at most this often (diagnostic_aggregator expects about 1 Hz), and at once when
#: what it says changes.
DIAGNOSTICS_PERIOD_S = 1.0


class SimClock:
    """The robot's simulated time, from rosgraph_msgs/Clock on /clock (--use-sim-time).

    A snapshot taken `d` seconds of wall time after the newest /clock message arrived is stamped
    that message's time plus `d` (a real-time factor of 1 between two /clock messages). Until the
    first message arrives the stamp is the wall time, with one warning."""

    def __init__(self) -> None:
        self.latest: tuple[float, float] | None = None  # (sim seconds, wall seconds it arrived)
        self._warned = False

    def take(self, message: Any) -> None:
        self.latest = (message.clock.sec + message.clock.nanosec * 1e-9, time.time())

    def stamp(self, wall: float) -> float:
        if self.latest is None:
            if not self._warned:
                log.warning("--use-sim-time: no message on /clock yet: stamping with the wall clock")
                self._warned = True
            return wall
        sim, arrived = self.latest
        return sim + (wall - arrived)


class Publisher:
    """The bridge's DDS writers; publish() turns one snapshot into every topic's message."""

    def __init__(
        self, node: Node, style: Style, prefix: str = "/drvs", profile: str = "reliable", clock: SimClock | None = None
    ) -> None:
        self.style = style
        self.prefix = prefix
        self.clock = clock
        self.markers = MarkerState()
        #: Per topic, the subscribers matched now (Cyclone's publication-matched status): a topic
        #: none reads is not made.
        self.matched = dict.fromkeys(output_topics(prefix), 0)
        self.writers = {
            topic: node.writer(topic, kind, profile, _on_matched(self.matched, topic))
            for topic, kind in output_topics(prefix).items()
        }
        self._diagnosed: tuple[Any, ...] = ()
        self._diagnosed_at = -math.inf
        self.published = 0

    def _diagnostics_due(self, snapshot: Snapshot) -> bool:
        said = (
            tuple(sorted((m.camera_id, m.code) for m in snapshot.camera_errors.values())),
            tuple(sorted(snapshot.camera_ids)),
            round(sum(p.area for p in snapshot.uncovered), 3),
        )
        now = time.monotonic()
        if said != self._diagnosed or now - self._diagnosed_at >= DIAGNOSTICS_PERIOD_S:
            self._diagnosed, self._diagnosed_at = said, now
            return True
        return False

    def publish(self, snapshot: Snapshot) -> None:
        at = snapshot.time if self.clock is None else self.clock.stamp(snapshot.time)
        read = {topic for topic, count in self.matched.items() if count}
        for topic, payload in snapshot_payloads(
            snapshot, self.style, self.markers, at, self.prefix, with_diagnostics=self._diagnostics_due(snapshot),
            topics=read,
        ):  # fmt: skip
            write_cdr(self.writers[topic], payload)
        self.published += 1


def _on_matched(counts: dict[str, int], topic: str) -> Listener:
    """A DDS listener keeping `counts[topic]` at the writer's matched subscribers (Cyclone's thread)."""

    def matched(writer: Any, status: Any) -> None:
        counts[topic] = status.current_count

    return Listener(on_publication_matched=matched)  # type: ignore[no-untyped-call]


def _on_data(loop: asyncio.AbstractEventLoop, handle: Callable[[Any], None]) -> Listener:
    """A DDS listener that hands each sample to `handle` on the event loop's thread."""

    def available(reader: Any) -> None:
        for sample in reader.take(16):
            loop.call_soon_threadsafe(handle, sample)

    return Listener(on_data_available=available)  # type: ignore[no-untyped-call]


@dataclass
class Following:
    """What the bridge asks DRVS: the filter, the region (changed live), the rate and the track's
    fusion options; `duration_s` 0 runs until stopped."""

    filter_def: str
    region: Polygon
    rate_hz: float
    duration_s: float = 0.0
    drop_after_s: float | None = None
    deadline_s: float | None = None


class Bridge:
    """Follows `following` with `client` and publishes through `publisher`; reads /<prefix>/region
    (and /clock with a SimClock) on `node`. `echo`: print each snapshot published as a JSON line."""

    def __init__(
        self, client: DrvsClient, node: Node, publisher: Publisher, following: Following, *, echo: bool = False
    ) -> None:
        self.client = client
        self.echo = echo
        self.node = node
        self.publisher = publisher
        self.following = following
        self._regions: asyncio.Queue[Polygon] = asyncio.Queue()
        self._readers: list[Any] = []
        self.tracks = 0
        self._this_track = 0

    def _region_message(self, message: Any) -> None:
        try:
            region = region_from_msg(message, self.publisher.style.frame_id)
        except InvalidArgument as exc:
            log.warning("%s/region: refused, the region stays as it was: %s", self.publisher.prefix, exc)
            return
        self._regions.put_nowait(region)

    def _listen(self) -> None:
        loop = asyncio.get_running_loop()
        topic = f"{self.publisher.prefix}/region"
        reader = self.node.reader(topic, REGION_TYPE)
        reader.set_listener(_on_data(loop, self._region_message))
        self._readers.append(reader)
        if self.publisher.clock is not None:
            clock = self.node.reader(*CLOCK_TOPIC, profile="sensor")
            clock.set_listener(_on_data(loop, self.publisher.clock.take))
            self._readers.append(clock)

    async def _follow(self, region: Polygon, seconds: float) -> None:
        """One track over `region` for `seconds`, each snapshot published as it comes."""
        f = self.following
        self._this_track = 0
        async with self.client.track(
            f.filter_def,
            list(region.exterior.coords)[:-1],
            rate_hz=f.rate_hz,
            duration_s=seconds,
            drop_after_s=f.drop_after_s,
            deadline_s=f.deadline_s,
        ) as track:
            self.tracks += 1
            log.info(
                "track %s over %s: dispatched to %s; publishing under %s",
                track.request_id,
                region.wkt,
                ", ".join(track.camera_ids) or "no camera",
                self.publisher.prefix,
            )
            async for snapshot in track:
                self.publisher.publish(snapshot)
                self._this_track += 1
                if self.echo:  # what was published, as drvs-robot track --json prints it
                    print(json.dumps(snapshot_json(snapshot)), flush=True)

    async def run(self) -> None:
        """Until stopped (or for `duration_s`): a track after another, a new one when the region changes.
        A track lost after it published is asked again (with the client's retry policy); Unavailable
        when a track is lost before its first snapshot, or none can be opened."""
        self._listen()
        loop = asyncio.get_running_loop()
        ends = loop.time() + self.following.duration_s if self.following.duration_s else math.inf
        while (left := ends - loop.time()) > 0:
            follow = asyncio.ensure_future(self._follow(self.following.region, min(left, MAX_DURATION_S)))
            change = asyncio.ensure_future(self._regions.get())
            try:
                done, _ = await asyncio.wait({follow, change}, return_when=asyncio.FIRST_COMPLETED)
            except asyncio.CancelledError:  # stopped: the track is closed at the server on the way out
                for task in (follow, change):
                    task.cancel()
                await asyncio.gather(follow, change, return_exceptions=True)
                raise
            if change in done:
                follow.cancel()
                await asyncio.gather(follow, return_exceptions=True)
                self.following.region = change.result()
                log.info("region changed to %s", self.following.region.wkt)
                continue
            change.cancel()
            try:
                follow.result()
            except Unavailable as exc:
                if not self._this_track:  # never opened, or lost before its first snapshot: give up
                    raise
                log.warning("the track ended early (%s): asking again", exc)
