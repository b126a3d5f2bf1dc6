"""Shares of a camera's requests: what one robot, or one callback listener, may hold at once.

A camera serves at most MAX_ACTIVE_REQUESTS requests at a time. Without shares, one caller could
hold them all: a robot whose listener never reads its reports keeps each of its single shots
waiting up to the report write timeout, and a few hundred such requests refuse every other robot
(the camera answers `busy`, and the server, hearing its camera is full, sheds everyone's requests
alike). So each holder (the robot as the server knows it, and, for reports to a robot, the callback
address) may hold at most a fair share: MAX_ACTIVE_REQUESTS over one more than the holders present,
never below MIN_SHARE. The share shrinks as holders arrive and always leaves room for a newcomer. A
refusal for a share names the holder and carries no retry hint: it is that caller's cap, not the
camera's load, so the server does not shed other robots' requests for it.

On top, a robot's continuous requests are capped (`max_continuous`), as before.
"""

from __future__ import annotations

import asyncio
from collections.abc import Hashable

from drvs.core.errors import ResourceExhausted

#: Concurrent requests a node serves at once; more are refused with RESOURCE_EXHAUSTED.
MAX_ACTIVE_REQUESTS = 512
#: The least share any holder may take, whatever the number of holders.
MIN_SHARE = 16

#: Whom a request counts for: ("robot", requester), or ("server", requester) for a fused request's
#: (without a requester: the callback address, or ("server", robot id)).
Robot = str | tuple[str, str]


def robot_name(robot: Robot) -> str:
    """Whom a request's share counts for, for a message."""
    if isinstance(robot, tuple):
        return f"robot {robot[1]!r}" + (" (fused, via the server)" if robot[0] == "server" else "")
    return robot


class _Counts:
    """Active requests per holder."""

    __slots__ = ("held",)

    def __init__(self) -> None:
        self.held: dict[Hashable, int] = {}

    def share(self, total: int) -> int:
        return max(MIN_SHARE, total // (len(self.held) + 1))

    def add(self, key: Hashable) -> None:
        self.held[key] = self.held.get(key, 0) + 1

    def remove(self, key: Hashable) -> None:
        left = self.held.get(key, 0) - 1
        if left > 0:
            self.held[key] = left
        else:
            self.held.pop(key, None)


class Shares:
    """The camera's active requests, counted per robot, per callback address and per robot's
    continuous requests; `check` before starting a request, `hold` with its task once started."""

    def __init__(self, camera_id: str, max_continuous: int, max_active: int = MAX_ACTIVE_REQUESTS) -> None:
        self.camera_id = camera_id
        self.max_continuous = max_continuous
        self.max_active = max_active
        self.active = 0
        self._robots = _Counts()
        self._callbacks = _Counts()
        self._continuous = _Counts()

    def check(self, robot: Robot, callback: str, continuous: bool) -> None:
        """ResourceExhausted if the camera is full, or `robot` (or its `callback`, "" for reports to
        a server) holds its share, or `robot` runs as many continuous requests as it may."""
        if self.active >= self.max_active:
            # Out of room: a hint, which also tells the server this is its load, not a caller's cap.
            raise ResourceExhausted(
                f"camera {self.camera_id}: {self.active} requests active; try later", retry_after_s=0.1
            )
        self._within(self._robots, robot, robot_name(robot), "requests active here", "wait for their reports")
        if callback:
            who = f"callback_address {callback}"
            self._within(self._callbacks, callback, who, "requests' reports pending here", "is it reading them?")
        running = self._continuous.held.get(robot, 0)
        if continuous and running >= self.max_continuous:
            raise ResourceExhausted(
                f"camera {self.camera_id}: continuous: {running} continuous requests already "
                f"running for {robot_name(robot)} (limit {self.max_continuous}); wait for one to end or cancel one"
            )

    def _within(self, counts: _Counts, key: Hashable, who: str, holding: str, advice: str) -> None:
        held, share = counts.held.get(key, 0), counts.share(self.max_active)
        if held >= share:
            raise ResourceExhausted(
                f"camera {self.camera_id}: {who} already has {held} {holding} (its share: {share}); {advice}"
            )

    def hold(self, job: asyncio.Task[None], robot: Robot, callback: str, continuous: bool) -> None:
        """Count a started request's `job` until it is done."""
        self.active += 1
        self._robots.add(robot)
        if callback:
            self._callbacks.add(callback)
        if continuous:
            self._continuous.add(robot)

        def done(_job: asyncio.Task[None]) -> None:
            self.active -= 1
            self._robots.remove(robot)
            if callback:
                self._callbacks.remove(callback)
            if continuous:
                self._continuous.remove(robot)

        job.add_done_callback(done)

    def continuous_running(self, robot: Robot) -> int:
        """Continuous requests running here for `robot`."""
        return self._continuous.held.get(robot, 0)

    def continuous(self) -> dict[Hashable, int]:
        """Continuous requests running here, by robot."""
        return dict(self._continuous.held)
