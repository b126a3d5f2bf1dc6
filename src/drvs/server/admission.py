"""Admission: the server refuses at its door what it or a camera cannot take now, before anything
is forwarded, so that past capacity it keeps answering at capacity instead of queueing until every
answer is late (Google SRE's "Handling Overload"; CoDel's standing-queue signal; AIMD).

Two queues decide. The server's own is its event loop: every request waits there, so the loop's
scheduling lag is its queue delay (`LoopLag`). A camera's is behind its link: a forward's round
trip beyond the fastest one lately seen is the time it waited in the camera's loop or on the way.
Each feeds a `Shedder`, which refuses a share of the requests while a queue *stands* (even the
shortest delay of an interval was above the target: a burst drains within one, a standing queue
does not), and admits more again once it has drained. The share moves as TCP's window does:
cut by a factor while a queue stands, grown by a step while none does.

Shedding is fair between callers (`FairShares`): when only a share of all requests can be admitted,
each caller (a robot's credential, or its connection) is admitted a max-min fair part of it, so a
caller sending far more than the others is refused first and the others, below their fair part, are
not refused at all. Without that, one flooding caller would make the door refuse everyone alike.

Pure logic but for LoopLag's task: the clock is injectable, so the control law is testable alone.
"""

from __future__ import annotations

import asyncio
import math
import random
import time
from collections.abc import Callable, Iterable

from drvs.core.errors import ResourceExhausted
from drvs.wire.metrics import ADMISSION_REFUSED as refused

#: CoDel's interval: a queue that stays this long above the target is standing, not a burst.
INTERVAL_S = 0.1
#: Standing queue delay tolerated before shedding, seconds: the server's loop, and a camera link
#: beyond its fastest round trip (drvs-server --admission-target; 0 turns admission off).
DEFAULT_TARGET_S = 0.01
LOOP_TARGET_S = LINK_TARGET_S = DEFAULT_TARGET_S
#: How often the loop's lag is sampled, seconds (a timer callback: about 1 µs of work each).
LOOP_TICK_S = 0.005
#: Per interval with a standing queue the admitted share is multiplied by this; per interval
#: without, it grows by ADMIT_STEP.
ADMIT_CUT = 0.75
ADMIT_STEP = 0.05
#: The share admitted never falls below this: some requests keep probing whether the queue drained.
MIN_ADMIT = 0.05
#: A link's base round trip is the fastest of the last two windows of this length.
BASE_WINDOW_S = 10.0
#: A forward counts as queued only if this many others were waiting on its link when it was sent,
#: and the loop's lag only while at least LOOP_MIN_ARRIVALS requests came in the last interval:
#: a lone request delayed because the host is busy with other work is no queue of requests, and
#: shedding it would not shorten anything.
LINK_MIN_WAITING = 8
LOOP_MIN_ARRIVALS = 10
#: A link's interval stands only on at least this many samples: a few requests caught behind one
#: stall of a camera (a heavy detector holding its loop, a busy host) are no standing queue (a
#: camera that refuses for room counts regardless).
LINK_MIN_SAMPLES = 8


#: A camera link's last 1/QUEUE_RESERVE of --max-queued-forwards is kept for callers below their
#: fair part (Door.check_queue).
QUEUE_RESERVE = 4

#: Callers whose arrival rates are tracked at once; past this, new ones share one bucket (and so,
#: together, one fair part: spraying identities buys no more than one).
MAX_CALLERS = 4096
#: Per interval, a caller's rate estimate moves this far towards what it sent in the interval.
RATE_WEIGHT = 0.5
#: A caller whose estimate falls below this (requests an interval) is forgotten.
RATE_FLOOR = 0.01
OTHERS = "\x00others"
#: Every caller not yet measured (first seen this interval), as one: its arrivals this interval.
NEW = "\x00new"


class FairShares:
    """Per-caller arrival rates, and how likely each caller is to be admitted when only `share` of
    all requests can be: max-min fair (water-filling). With rates r_i and budget B = share * sum(r),
    the fair level f solves sum(min(r_i, f)) = B; caller i is admitted with probability
    min(1, f / r_i). Equal callers are all admitted `share`, as with no fairness; a caller at twice
    the others' rate loses its excess first.

    Callers not yet measured (first seen in this interval) are, together, one caller whose rate is
    their arrivals so far this interval: a robot that joins while another floods is admitted as the
    modest caller it is, not refused its first requests at the flood's share; identities sprayed to
    look new share about one part an interval (the k-th new arrival is admitted level / k), as those
    past `max_callers` share one. Before anything is measured every caller is admitted `share`."""

    __slots__ = ("_clock", "_counts", "_levels", "_rates", "_sorted", "_until", "interval_s", "max_callers")

    def __init__(
        self,
        interval_s: float = INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
        max_callers: int = MAX_CALLERS,
    ) -> None:
        self.interval_s = interval_s
        self.max_callers = max_callers
        self._clock = clock
        self._counts: dict[str, int] = {}  # arrivals in the current interval
        self._rates: dict[str, float] = {}  # arrivals an interval, smoothed
        self._sorted: list[float] = []
        self._levels: dict[float, float] = {}  # share -> fair level, for the rates now
        self._until = clock() + interval_s

    def arrived(self, caller: str) -> None:
        self._roll()
        counts = self._counts
        if caller not in self._rates:
            if caller not in counts and len(self._rates) + len(counts) >= self.max_callers:
                caller = OTHERS
            elif caller != OTHERS:
                counts[NEW] = counts.get(NEW, 0) + 1
        counts[caller] = counts.get(caller, 0) + 1

    def admit(self, caller: str, share: float) -> float:
        """The probability of admitting `caller`'s request now, when `share` of all can be."""
        if share >= 1.0:
            return 1.0
        self._roll()
        rates = self._rates
        rate = rates.get(caller, 0.0)
        if not rate:
            if caller in self._counts:
                rate = float(self._counts.get(NEW, 0))
            else:  # past max_callers: their bucket's
                rate = max(rates.get(OTHERS, 0.0), float(self._counts.get(OTHERS, 0)))
        if rate <= 0.0 or not self._sorted:
            return share
        level = self._levels.get(share)
        if level is None:
            level = self._levels[share] = self._level(share)
        return min(1.0, level / rate)

    def rate(self, caller: str) -> float:
        """`caller`'s smoothed arrivals an interval (0: not measured)."""
        self._roll()
        return self._rates.get(caller, 0.0)

    def _level(self, share: float) -> float:
        rates = self._sorted
        budget = share * sum(rates)
        below, n = 0.0, len(rates)
        for k, rate in enumerate(rates):
            if below + (n - k) * rate >= budget:
                return (budget - below) / (n - k)
            below += rate
        return math.inf

    def _roll(self) -> None:
        now = self._clock()
        if now < self._until:
            return
        passed = 1 + int((now - self._until) / self.interval_s)
        keep = (1.0 - RATE_WEIGHT) ** passed
        rates = {caller: rate * keep for caller, rate in self._rates.items()}
        fresh = RATE_WEIGHT * (1.0 - RATE_WEIGHT) ** (passed - 1)
        for caller, count in self._counts.items():
            if caller != NEW:  # (its arrivals are in their callers' counts too)
                rates[caller] = rates.get(caller, 0.0) + fresh * count
        self._rates = {caller: rate for caller, rate in rates.items() if rate >= RATE_FLOOR}
        self._sorted = sorted(self._rates.values())
        self._levels = {}
        self._counts = {}
        self._until = now + self.interval_s


class Shedder:
    """Decides what share of requests to admit from queue-delay samples (see the module)."""

    __slots__ = ("_clock", "_min", "_samples", "_until", "admit", "interval_s", "min_samples", "target_s")

    def __init__(
        self,
        target_s: float,
        interval_s: float = INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
        min_samples: int = 1,
    ) -> None:
        self.target_s = target_s
        self.interval_s = interval_s
        self.min_samples = min_samples
        self._samples = 0
        self._clock = clock
        #: The share of requests admitted now, in [MIN_ADMIT, 1].
        self.admit = 1.0
        self._min = math.inf  # the shortest delay seen in the current interval
        self._until = clock() + interval_s

    def observe(self, delay_s: float) -> None:
        """A queue-delay sample (seconds)."""
        self._roll()
        self._samples += 1
        if delay_s < self._min:
            self._min = delay_s

    def congested(self) -> None:
        """A peer refused for lack of room: the queue stands whatever the delays said."""
        self._roll()
        self._min = math.nan  # marks the interval as standing: no later sample compares below it
        self._samples = max(self._samples, self.min_samples)

    def share(self) -> float:
        """The share of requests to admit now."""
        self._roll()
        return self.admit

    def _roll(self) -> None:
        now = self._clock()
        if now < self._until:
            return
        # nan: told congested; too few samples: a stall, not a queue.
        standing = self._samples >= self.min_samples and self._min != math.inf and not self._min <= self.target_s
        if standing:
            self.admit = max(MIN_ADMIT, self.admit * ADMIT_CUT)
        else:
            # Intervals with no sample at all (idle, or everything refused) count as drained.
            passed = 1 + int((now - self._until) / self.interval_s)
            self.admit = min(1.0, self.admit + ADMIT_STEP * passed)
        self._min = math.inf
        self._samples = 0
        self._until = now + self.interval_s


class LinkDelay:
    """A camera link's queue delay: each forward's round trip beyond the fastest one of the last
    one or two BASE_WINDOW_S (a link that got slower for good moves its base within 20 s)."""

    __slots__ = ("_base", "_clock", "_previous", "_window_end", "shedder")

    def __init__(self, target_s: float = LINK_TARGET_S, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self.shedder = Shedder(target_s, clock=clock, min_samples=LINK_MIN_SAMPLES)
        self._base = math.inf
        self._previous = math.inf
        self._window_end = clock() + BASE_WINDOW_S

    def observe(self, round_trip_s: float, waiting: int) -> None:
        """A forward's round trip, and how many forwards were waiting on the link when it was sent."""
        now = self._clock()
        if now >= self._window_end:
            self._previous, self._base = self._base, math.inf
            self._window_end = now + BASE_WINDOW_S
        self._base = min(self._base, round_trip_s)
        queued = waiting >= LINK_MIN_WAITING
        self.shedder.observe(round_trip_s - min(self._base, self._previous) if queued else 0.0)


class LoopLag:
    """Samples the running event loop's scheduling lag into a Shedder: how late a timer set for
    LOOP_TICK_S fires is how long any callback, a request's included, waits for the loop now.
    Counted only while requests arrive (`arrived()`, at least LOOP_MIN_ARRIVALS an interval)."""

    def __init__(self, target_s: float = LOOP_TARGET_S) -> None:
        self.shedder = Shedder(target_s)
        self._task: asyncio.Task[None] | None = None
        #: The last lag measured, seconds.
        self.last_s = 0.0
        self._arrivals = 0  # requests in the current interval
        self._busy = False  # enough of them in the last interval

    def arrived(self) -> None:
        self._arrivals += 1

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        interval_end = loop.time() + INTERVAL_S
        while True:
            # While too few requests come for their lag to count, one tick an interval: a timer 200
            # times a second cost an idle server 1.5 % of a core, half a millisecond per request at 30 Hz.
            period = LOOP_TICK_S if self._busy or self._arrivals >= LOOP_MIN_ARRIVALS else INTERVAL_S
            due = loop.time() + period
            await asyncio.sleep(period)
            now = loop.time()
            self.last_s = max(0.0, now - due)
            if now >= interval_end:
                self._busy, self._arrivals = self._arrivals >= LOOP_MIN_ARRIVALS, 0
                interval_end = now + INTERVAL_S
            self.shedder.observe(self.last_s if self._busy or self._arrivals >= LOOP_MIN_ARRIVALS else 0.0)


class Door:
    """The server's admission: a request is admitted with the smallest share of the server's loop
    and of every camera link it needs; the rest are refused with ResourceExhausted and a retry
    hint, before anything is forwarded. `draw` is the random source (tests pass their own)."""

    def __init__(self, target_s: float = DEFAULT_TARGET_S, draw: Callable[[], float] = random.random) -> None:
        #: 0: admission off (every request passes; the fixed bounds, such as a link's queue, stay).
        self.target_s = target_s
        self.loop = LoopLag(target_s)
        #: Fused single shots' answers (dispatch to snapshot) beyond the fastest: the queue of the
        #: cameras' reports to the server, which no forward's acknowledgement shows.
        self.fused = LinkDelay(target_s)
        #: Who is refused first when only a share can be admitted.
        self.fair = FairShares()
        self._draw = draw

    def start(self) -> None:
        if self.target_s > 0:
            self.loop.start()

    def link(self) -> LinkDelay:
        """A new camera link's delay, shedding at this door's target."""
        return LinkDelay(self.target_s)

    def check_server(self, caller: str = "") -> None:
        """First, before a request is even read whole: ResourceExhausted if the server's own loop
        sheds this one. `caller`: whom the request counts for (see FairShares)."""
        if not self.target_s:
            return
        self.loop.arrived()
        self.fair.arrived(caller)
        admit = self.loop.shedder.share()
        if admit < 1.0 and self._draw() >= self.fair.admit(caller, admit):
            refused("server").inc()
            hint = retry_after_s(admit)
            raise ResourceExhausted(
                f"overloaded: the server is past its capacity (admitting {admit:.0%} of requests); "
                f"retry in {hint * 1000:.0f} ms",
                retry_after_s=hint,
            )

    def check_queue(self, camera_id: str, waiting: int, most: int, caller: str = "") -> None:
        """ResourceExhausted if a camera link with `waiting` forwards (of at most `most`) cannot take
        `caller`'s request. At `most`, nobody's. In its last quarter (QUEUE_RESERVE), a fair part of a
        share that falls from 1 to 0 as it fills: a caller flooding the link is refused there, so
        that its requests do not fill the link to the limit, where everyone is refused alike."""
        reserve = most // QUEUE_RESERVE if self.target_s else 0
        if waiting < most - reserve:
            return
        if waiting < most:
            share = (most - waiting) / (reserve + 1)
            if self._draw() < self.fair.admit(caller, share):
                return
        refused("queue").inc()
        raise ResourceExhausted(
            f"busy: camera {camera_id} has {waiting} requests already waiting for it (limit {most}); retry in 100 ms",
            retry_after_s=0.1,
        )

    def check_cameras(self, links: Iterable[tuple[str, Shedder]], fused: bool = False, caller: str = "") -> None:
        """Then, once routed: ResourceExhausted if a camera the request needs sheds it (or, for a
        fused request, fused delivery does); `links` are (camera id, its link's shedder) for the
        cameras it would be forwarded to. One draw for all of them, against the smallest share: a
        request is as admissible as its busiest camera (and its caller's fair part of that share)."""
        if not self.target_s:
            return
        admit, who, by = 1.0, "", "camera"
        for camera_id, shedder in links:
            share = shedder.share()
            if share < admit:
                admit, who = share, f"camera {camera_id}"
        if fused and (share := self.fused.shedder.share()) < admit:
            admit, who, by = share, "fused delivery", "fused"
        if admit < 1.0 and self._draw() >= self.fair.admit(caller, admit):
            refused(by).inc()
            hint = retry_after_s(admit)
            raise ResourceExhausted(
                f"overloaded: {who} is past what it can take now (admitting {admit:.0%} of its requests); "
                f"retry in {hint * 1000:.0f} ms",
                retry_after_s=hint,
            )


def retry_after_s(admit: float) -> float:
    """The wait a refusal asks for: one interval, longer the less is admitted (at most 0.5 s), so a
    fleet of robots backs off about as much as the server sheds."""
    return round(INTERVAL_S * (1 + 4 * (1 - admit)), 3)
