"""Client-side adaptive throttling (Google SRE book, "Handling Overload"): a robot whose server
refuses it for overload refuses its own requests first, in proportion, so a fleet converges to
what the server can take instead of hammering it with requests it will refuse anyway.

Over the last `window_s` the client counts the requests its code made (`requests`, those it refused
itself included) and those the server accepted (`accepts`). A new request is refused locally with
probability max(0, (requests - k * accepts) / (requests + 1)). While the server accepts everything
that is 0; once it refuses, the client lets through about k times what it accepts, so the server
still sees enough to notice when it has room again. Pure logic; the clock and the random draw are
injectable.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable

from drvs.core.errors import InvalidArgument, ResourceExhausted

#: The SRE book's multiplier: the server sees up to twice what it accepts.
DEFAULT_K = 2.0
DEFAULT_WINDOW_S = 10.0
#: The window is kept as this many buckets.
BUCKETS = 10
#: Nothing is held back until the server has refused at least this many more requests than k times
#: those it accepted: at a robot's first requests one slow answer would otherwise hold back half of
#: the next ((1 - 0) / (1 + 1)), which is no sign of overload.
MIN_EXCESS = 10


class AdaptiveThrottle:
    """Refuses requests locally in proportion to the server's recent refusals (see the module)."""

    def __init__(
        self,
        k: float = DEFAULT_K,
        window_s: float = DEFAULT_WINDOW_S,
        *,
        clock: Callable[[], float] = time.monotonic,
        draw: Callable[[], float] = random.random,
    ) -> None:
        if not (isinstance(k, (int, float)) and k >= 1.0):
            raise InvalidArgument(
                f"throttle_k: {k!r} must be a number >= 1 (2 is the usual; larger throttles later; inf: never)"
            )
        if not (isinstance(window_s, (int, float)) and math.isfinite(window_s) and window_s > 0):
            raise InvalidArgument(f"throttle window: {window_s!r} must be a positive number of seconds")
        self.k = float(k)
        self._bucket_s = window_s / BUCKETS
        self._clock = clock
        self._draw = draw
        self._requests = [0] * BUCKETS
        self._accepts = [0] * BUCKETS
        self._index = 0
        self._bucket_end = clock() + self._bucket_s
        #: Requests refused here without being sent, since the client started.
        self.refused_locally = 0

    def _advance(self) -> None:
        now = self._clock()
        if now < self._bucket_end:
            return
        steps = min(BUCKETS, 1 + int((now - self._bucket_end) / self._bucket_s))
        for _ in range(steps):
            self._index = (self._index + 1) % BUCKETS
            self._requests[self._index] = 0
            self._accepts[self._index] = 0
        self._bucket_end = now + self._bucket_s

    def reject_probability(self) -> float:
        if self.k == math.inf:
            return 0.0  # off: a tool that measures the server itself sends everything
        self._advance()
        requests = sum(self._requests)
        excess = requests - self.k * sum(self._accepts)
        return excess / (requests + 1) if excess >= MIN_EXCESS else 0.0

    def check(self, what: str) -> None:
        """Count a request `what` about to be sent; ResourceExhausted if it is refused here."""
        p = self.reject_probability()
        self._requests[self._index] += 1
        if p > 0.0 and self._draw() < p:
            self.refused_locally += 1
            raise ResourceExhausted(
                f"{what}: not sent: the server is refusing this robot's requests for overload, so the "
                f"client holds back {p:.0%} of them itself (client-side throttling)"
            )

    def accepted(self) -> None:
        """The server took the request counted last."""
        self._advance()
        self._accepts[self._index] += 1
