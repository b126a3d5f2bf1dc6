"""Exponential backoff, written once: waits that double from a first one up to a longest one, and
start again from the first after a success. Every retry loop in DRVS takes its waits from here (a
camera's registration and heartbeats, a pose feed's reconnects, the scout's pose stream, the shared
registry's watch of etcd, the robot's RetryPolicy and a track's resumption)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator


def waits(initial_s: float, max_s: float, count: int) -> Iterator[float]:
    """`count` waits, seconds: initial_s, then each double the one before, never above max_s."""
    backoff = Backoff(initial_s, max_s)
    for _ in range(count):
        yield backoff.next()


class Backoff:
    """The waits of one retry loop: `next()` after each failure, `reset()` after a success.

    `next(max_s=...)` caps the wait after this one differently for one failure (a camera refused
    its id backs off longer than one that found the server down)."""

    __slots__ = ("_next", "initial_s", "max_s")

    def __init__(self, initial_s: float, max_s: float) -> None:
        if not 0 < initial_s <= max_s:
            raise ValueError(f"backoff: need 0 < initial_s ({initial_s}) <= max_s ({max_s})")
        self.initial_s = initial_s
        self.max_s = max_s
        self._next = initial_s

    @property
    def current(self) -> float:
        """The wait the next failure takes, seconds."""
        return self._next

    @property
    def failing(self) -> bool:
        """Has a failure come since the last success (the next wait is no longer the first)?"""
        return self._next != self.initial_s

    def next(self, max_s: float | None = None) -> float:
        """The wait for this failure; the one after it doubles, up to `max_s` (default: the loop's)."""
        wait = self._next
        self._next = min(wait * 2, self.max_s if max_s is None else max_s)
        return wait

    def reset(self) -> None:
        """A success: the next failure waits the first wait again."""
        self._next = self.initial_s

    async def sleep(self, max_s: float | None = None) -> float:
        """Wait this failure's wait (`next`); returns it."""
        wait = self.next(max_s)
        await asyncio.sleep(wait)
        return wait
