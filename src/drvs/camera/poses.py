"""Pose sources: where a mobile camera node reads its robot's poses (`drvs-camera --pose-source`).

- ``tcp://HOST:PORT``: a newline-delimited JSON feed. The node connects and reads one object a
  line, ``{"t": <seconds since the Unix epoch>, "x": <m>, "y": <m>, "yaw": <rad>}`` (the robot's
  base in the map frame, yaw counter-clockwise from +x, t on the same clock as the frames'
  capture times). A line that is not such an object is logged (at most once a second) and
  skipped; a dropped connection is reopened with backoff.
- Other schemes come from installed plug-ins: the entry-point group ``drvs.pose_sources``, name
  the scheme, value a class built as ``cls(spec)`` with ``description`` and
  ``async def run(self, push)``, ``push(t, Pose2)`` for each pose, running until cancelled.
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import json
import logging
import math
import time
from typing import Protocol

from drvs.core.backoff import Backoff
from drvs.core.errors import DrvsError, InvalidArgument
from drvs.core.mobile import INITIAL_BACKOFF_S, MAX_BACKOFF_S, Push
from drvs.core.model import Pose2
from drvs.core.net import parse_address

log = logging.getLogger("drvs.camera.poses")

POSE_ENTRY_POINT_GROUP = "drvs.pose_sources"
#: Longest line the feed may send, bytes.
MAX_LINE_BYTES = 4096


class PoseSource(Protocol):
    description: str

    async def run(self, push: Push) -> None: ...


def parse_pose_line(line: bytes | str) -> tuple[float, Pose2]:
    """One line of the tcp:// feed: (t, pose); InvalidArgument naming what is wrong."""
    try:
        data = json.loads(line)
    except (ValueError, UnicodeDecodeError):
        raise InvalidArgument(f"pose line: not JSON: {line[:80]!r}") from None
    if not isinstance(data, dict):
        raise InvalidArgument(f"pose line: expected an object with t, x, y, yaw; got {type(data).__name__}")
    values = []
    for key in ("t", "x", "y", "yaw"):
        value = data.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InvalidArgument(f"pose line: {key}: {value!r} is not a finite number")
        values.append(float(value))
    t, x, y, yaw = values
    return t, Pose2(x, y, yaw)


class TcpPoseSource:
    """The tcp://HOST:PORT newline-delimited JSON feed (see the module docstring)."""

    def __init__(self, spec: str) -> None:
        self.address = spec[len("tcp://") :]
        self.host, self.port = parse_address(self.address, "--pose-source")
        self.description = spec
        self.poses = 0
        self.bad_lines = 0
        self._last_complaint = 0.0

    async def run(self, push: Push) -> None:
        backoff = Backoff(INITIAL_BACKOFF_S, MAX_BACKOFF_S)
        while True:
            try:
                reader, writer = await asyncio.open_connection(self.host, self.port, limit=MAX_LINE_BYTES)
            except OSError as exc:
                log.warning(
                    "pose source %s: cannot connect (%s); again in %.1f s", self.description, exc, backoff.current
                )
                await backoff.sleep()
                continue
            log.info("pose source %s: connected", self.description)
            backoff.reset()
            try:
                while line := await reader.readline():
                    self._take(line, push)
            except (OSError, ValueError) as exc:  # ValueError: a line beyond the limit
                log.warning("pose source %s: %s", self.description, exc)
            finally:
                writer.close()
            log.warning("pose source %s: connection closed; reconnecting", self.description)
            await asyncio.sleep(backoff.current)

    def _take(self, line: bytes, push: Push) -> None:
        if not line.strip():
            return
        try:
            t, pose = parse_pose_line(line)
            push(t, pose)
            self.poses += 1
        except DrvsError as exc:
            self.bad_lines += 1
            now = time.monotonic()
            if now - self._last_complaint >= 1.0:
                self._last_complaint = now
                log.warning("pose source %s: %s (%d bad lines so far)", self.description, exc, self.bad_lines)


def open_pose_source(spec: str) -> PoseSource:
    """The pose source `spec` names; InvalidArgument naming --pose-source when none can take it."""
    scheme, sep, _ = spec.partition("://")
    if not sep:
        raise InvalidArgument(f"--pose-source: {spec!r} has no scheme; expected tcp://HOST:PORT or sim://HOST:PORT/ID")
    if scheme == "tcp":
        return TcpPoseSource(spec)
    for entry in importlib.metadata.entry_points(group=POSE_ENTRY_POINT_GROUP, name=scheme):
        factory = entry.load()
        source: PoseSource = factory(spec)
        return source
    raise InvalidArgument(f"--pose-source: no pose source for {scheme}:// (tcp:// is built in)")
