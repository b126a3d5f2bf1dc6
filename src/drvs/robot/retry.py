"""RetryPolicy: how often the robot client tries a call the server could not take (Unavailable),
and the waits between (drvs.core.backoff)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import ClassVar, TypeVar

from drvs.core.backoff import waits
from drvs.core.errors import DeadlineExceeded, DrvsError, InvalidArgument, ResourceExhausted, Unavailable
from drvs.robot.limits import MAX_BACKOFF_S, seconds
from drvs.robot.throttle import AdaptiveThrottle

log = logging.getLogger("drvs.robot")

T = TypeVar("T")


@dataclass(frozen=True)
class RetryPolicy:
    """How often to try a call the server could not take (Unavailable: down, restarting, unreachable).

    - `attempts`: how many times in all a call is tried, the first included (1: no retry), at most 1000;
    - `initial_backoff_s`: seconds to wait before the second attempt, in (0, max_backoff_s];
    - `max_backoff_s`: the longest wait between attempts, seconds, in (0, 60]; each wait doubles
      the previous one up to this.

    It applies to DrvsClient.connect's check of the server and to each request's and cameras()
    call's wait for the server's reply; never to a call the server has answered (a refusal is final).
    `RetryPolicy.retries(n)` is the policy of n retries (n + 1 attempts) with the default backoff.
    """

    attempts: int = 1
    initial_backoff_s: float = 0.2
    max_backoff_s: float = MAX_BACKOFF_S

    MAX_ATTEMPTS: ClassVar[int] = 1000
    MAX_BACKOFF_LIMIT_S: ClassVar[float] = 60.0

    def __post_init__(self) -> None:
        if (
            isinstance(self.attempts, bool)
            or not isinstance(self.attempts, int)
            or not (1 <= self.attempts <= self.MAX_ATTEMPTS)
        ):
            raise InvalidArgument(
                f"retry.attempts: {self.attempts!r} must be a whole number in [1, {self.MAX_ATTEMPTS}] "
                "(the first try included)"
            )
        seconds(self.max_backoff_s, "retry.max_backoff_s", self.MAX_BACKOFF_LIMIT_S)
        seconds(self.initial_backoff_s, "retry.initial_backoff_s", self.max_backoff_s)

    @classmethod
    def retries(cls, count: int) -> RetryPolicy:
        """`count` retries after the first attempt, with the default backoff (drvs-robot --retries)."""
        if isinstance(count, bool) or not isinstance(count, int) or not (0 <= count < cls.MAX_ATTEMPTS):
            raise InvalidArgument(f"retries: {count!r} must be a whole number in [0, {cls.MAX_ATTEMPTS - 1}]")
        return cls(attempts=count + 1)

    def backoffs(self) -> Iterator[float]:
        """The waits (seconds) before the second, third ... attempt: attempts - 1 of them."""
        return waits(self.initial_backoff_s, self.max_backoff_s, self.attempts - 1)


async def retrying(policy: RetryPolicy, server: str, what: str, call: Callable[[], Awaitable[T]]) -> T:
    """`call()`, tried again after each Unavailable as `policy` allows (`server` and `what` name it in the log)."""
    backoffs = policy.backoffs()
    while True:
        try:
            return await call()
        except Unavailable:
            wait = next(backoffs, None)
            if wait is None:
                raise
            log.info("server %s unavailable; retrying %s in %.1f s", server, what, wait)
            await asyncio.sleep(wait)


async def asking(
    throttle: AdaptiveThrottle, policy: RetryPolicy, server: str, what: str, call: Callable[[], Awaitable[T]]
) -> T:
    """A request to the server through the client's throttle: refused at once while the server
    refuses this robot for overload (drvs.robot.throttle), else sent as `retrying` sends it; the
    server's answer is counted."""
    throttle.check(what)
    try:
        reply = await retrying(policy, server, what, call)
    except DrvsError as exc:
        # Refused for overload (the server's door gives a retry hint; a robot over its own
        # budget gets none) or not answered in time: not accepted. Anything else says nothing
        # of the server's load.
        overload = isinstance(exc, DeadlineExceeded) or (isinstance(exc, ResourceExhausted) and exc.retry_after_s > 0)
        if not overload:
            throttle.accepted()
        raise
    throttle.accepted()
    return reply
