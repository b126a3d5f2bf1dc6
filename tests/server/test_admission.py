"""Overload: the server refuses at its door, before any camera is asked, what a camera (or the
server itself) cannot take now, with RESOURCE_EXHAUSTED and a retry hint; robots throttle
themselves on those refusals. The control laws alone on a fake clock, then real processes: a
server and a camera that takes 10 ms a request, one at a time (a real queue), flooded."""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from drvs.core.errors import InvalidArgument, ResourceExhausted
from drvs.robot import DrvsClient
from drvs.robot.throttle import MIN_EXCESS, AdaptiveThrottle
from drvs.server.admission import (
    ADMIT_CUT,
    ADMIT_STEP,
    BASE_WINDOW_S,
    INTERVAL_S,
    LINK_MIN_SAMPLES,
    LINK_MIN_WAITING,
    MIN_ADMIT,
    Door,
    FairShares,
    LinkDelay,
    Shedder,
    retry_after_s,
)
from drvs.tools.launch import ManagedProcess, start_server
from tests.helpers import YELLOW

ROLES = Path(__file__).parents[1] / "fakes" / "fault_roles.py"
#: The queueing camera sees x 34..46, y 1.5..7.5 (fault_roles.py); a region inside it.
QUEUED_REGION = (38.0, 3.0, 42.0, 6.0)
QUEUEING = ("--accept-delay", "0.01", "--report-delay", "0")


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


# --- the control laws ---------------------------------------------------------------------------


def test_a_standing_queue_cuts_the_admitted_share_and_a_drained_one_restores_it() -> None:
    clock = Clock()
    shedder = Shedder(0.01, clock=clock)
    # A burst: one slow sample among fast ones is no standing queue.
    for delay in (0.002, 0.2, 0.001):
        shedder.observe(delay)
    clock.now += INTERVAL_S
    assert shedder.share() == 1.0
    # Every sample of an interval above the target: the queue stands, the share is cut.
    for delay in (0.03, 0.05, 0.02):
        shedder.observe(delay)
    clock.now += INTERVAL_S
    assert shedder.share() == pytest.approx(ADMIT_CUT)
    for _ in range(30):  # it stands on: cut each interval, never below the probing floor
        shedder.observe(0.05)
        clock.now += INTERVAL_S
    assert shedder.share() == MIN_ADMIT
    shedder.observe(0.001)  # drained
    clock.now += INTERVAL_S
    assert shedder.share() == pytest.approx(MIN_ADMIT + ADMIT_STEP)
    clock.now += 100 * INTERVAL_S  # idle: nothing stands, everything is admitted again
    assert shedder.share() == 1.0


def test_a_peer_that_refuses_for_room_counts_as_a_standing_queue() -> None:
    clock = Clock()
    shedder = Shedder(0.01, clock=clock)
    shedder.congested()
    shedder.observe(0.0)  # a fast answer in the same interval does not undo the refusal
    clock.now += INTERVAL_S
    assert shedder.share() == pytest.approx(ADMIT_CUT)


def test_a_link_measures_its_queue_above_its_fastest_round_trip() -> None:
    clock = Clock()
    link = LinkDelay(0.01, clock=clock)
    # A far camera: 80 ms every time is its distance, not a queue.
    queue = LINK_MIN_WAITING
    for _ in range(50):
        link.observe(0.080, queue)
    clock.now += INTERVAL_S
    assert link.shedder.share() == 1.0
    for _ in range(LINK_MIN_SAMPLES - 1):  # 30 ms more for a few requests behind one stall: no queue
        link.observe(0.110, queue)
    clock.now += INTERVAL_S
    assert link.shedder.share() == 1.0
    for _ in range(LINK_MIN_SAMPLES):  # then 30 ms more, all the time: a queue
        link.observe(0.110, queue)
    clock.now += INTERVAL_S
    assert link.shedder.share() == pytest.approx(ADMIT_CUT)
    # Slow but with few others on the link (the host is busy, not the camera's queue): no queue.
    for _ in range(LINK_MIN_SAMPLES):
        link.observe(0.300, LINK_MIN_WAITING - 1)
    clock.now += INTERVAL_S
    assert link.shedder.share() == pytest.approx(ADMIT_CUT + ADMIT_STEP)
    # A link that got slower for good: after two base windows its new round trip is its base.
    for _ in range(3):
        clock.now += BASE_WINDOW_S
        link.observe(0.110, queue)
    clock.now += 100 * INTERVAL_S
    link.observe(0.110, queue)
    clock.now += INTERVAL_S
    assert link.shedder.share() == 1.0


def test_the_door_draws_once_against_the_busiest_camera_and_hints_a_wait() -> None:
    clock = Clock()
    busy, idle = Shedder(0.01, clock=clock), Shedder(0.01, clock=clock)
    busy.admit = 0.3
    door = Door(draw=lambda: 0.5)
    with pytest.raises(ResourceExhausted, match=r"camera cam-b is past what it can take now \(admitting 30%") as info:
        door.check_cameras([("cam-a", idle), ("cam-b", busy)])
    assert info.value.retry_after_s == retry_after_s(0.3) > 0
    door = Door(draw=lambda: 0.2)  # within the admitted share
    door.check_cameras([("cam-a", idle), ("cam-b", busy)])
    door.check_server()  # the server's own loop stands no queue: everything passes
    door.loop.shedder.admit = 0.1
    with pytest.raises(ResourceExhausted, match="the server is past its capacity"):
        door.check_server()
    assert retry_after_s(1.0) == INTERVAL_S and retry_after_s(MIN_ADMIT) <= 0.5
    # A fused request also waits for fused answers' queue (the cameras' reports to the server).
    slow = Door(draw=lambda: 0.5)
    slow.fused.shedder.admit = 0.2
    slow.check_cameras([("cam-a", idle)])  # not fused: that queue is not its
    with pytest.raises(ResourceExhausted, match=r"overloaded: fused delivery is past what it can take now"):
        slow.check_cameras([("cam-a", idle)], fused=True)
    # --admission-target 0: the door is off, whatever the queues say.
    off = Door(0.0, draw=lambda: 0.99)
    off.loop.shedder.admit = MIN_ADMIT
    off.check_server()
    off.check_cameras([("cam-b", busy)])


def arrive(fair: FairShares, counts: tuple[tuple[str, int], ...]) -> None:
    """`fair` hears each (caller, count): count arrivals of that caller."""
    for caller, count in counts:
        for _ in range(count):
            fair.arrived(caller)


#: Rates 2, 2 and 46 an interval once measured: at 20 % admissible, a fair level of 6.
FLOODED = (("a", 4), ("b", 4), ("flood", 92))


def test_fair_shares_refuse_the_heaviest_caller_first() -> None:
    """Max-min fairness: rates 2, 2 and 46 a tenth of a second, 20 % admissible (a budget of 10):
    the two light callers stay under the fair level (6) and are always admitted, the heavy one gets
    what is left (6 of 46). Equal callers are each admitted the share, as without fairness."""
    clock = Clock()
    fair = FairShares(clock=clock)
    arrive(fair, FLOODED)
    assert fair.admit("a", 0.2) == 0.2  # nothing measured yet: the share, as without fairness
    clock.now += INTERVAL_S
    assert fair.rate("a") == pytest.approx(2) and fair.rate("flood") == pytest.approx(46)
    assert fair.admit("a", 0.2) == fair.admit("b", 0.2) == 1.0
    assert fair.admit("flood", 0.2) == pytest.approx(6 / 46)
    assert fair.admit("flood", 1.0) == 1.0
    # Expected admissions are the budget: 2 + 2 + 46 * 6 / 46 = 10 = 0.2 * 50.
    assert 2 + 2 + 46 * fair.admit("flood", 0.2) == pytest.approx(0.2 * 50)
    # Rates fade when a caller stops; forgotten once negligible.
    clock.now += 20 * INTERVAL_S
    assert fair.rate("flood") == 0.0
    equal = FairShares(clock=clock)
    for caller in ("x", "y") * 10:
        equal.arrived(caller)
    clock.now += INTERVAL_S
    assert equal.admit("x", 0.3) == pytest.approx(0.3) == equal.admit("y", 0.3)


def test_a_caller_that_joins_during_a_flood_is_admitted_as_the_modest_caller_it_is() -> None:
    """A robot first seen while another floods (20 % admissible, fair level 6 an interval) is
    admitted at once: its requests so far are far below the level. Before, a caller not yet measured
    was admitted only the share, so a robot joining a flooded server lost most of its first
    requests. Identities sprayed to look new count together, as one caller not yet measured: with
    28 more in one interval, each of the 30 new callers is admitted 6 / 30, not the share each."""
    clock = Clock()

    def flooded() -> FairShares:
        fair = FairShares(clock=clock)
        arrive(fair, FLOODED)
        clock.now += INTERVAL_S
        return fair

    fair = flooded()
    fair.arrived("joiner")
    assert fair.admit("joiner", 0.2) == 1.0 and fair.admit("flood", 0.2) == pytest.approx(6 / 46)
    fair.arrived("joiner")  # its second: still below the level
    assert fair.admit("joiner", 0.2) == 1.0
    # Measured at the next interval, on its own rate (two requests: 1 an interval), still admitted.
    arrive(fair, FLOODED)
    clock.now += INTERVAL_S
    assert fair.rate("joiner") == pytest.approx(1.0)
    fair.arrived("joiner")
    assert fair.admit("joiner", 0.2) == 1.0
    sprayed = flooded()
    for k in range(30):
        sprayed.arrived(f"spray{k}")
    assert sprayed.admit("spray0", 0.2) == pytest.approx(6 / 30) == sprayed.admit("spray29", 0.2)
    assert sprayed.admit("a", 0.2) == 1.0
    # Before anything is measured, nothing to be fair by: the share.
    fresh = FairShares(clock=clock)
    fresh.arrived("first")
    assert fresh.admit("first", 0.2) == 0.2


def test_a_links_last_quarter_is_kept_for_callers_below_their_fair_part() -> None:
    """A camera link with 64 forwards allowed: below 48 waiting everyone is admitted; from 48 a
    flooding caller is admitted a falling fair part of a falling share, a modest one still always;
    at 64 nobody. With admission off (--admission-target 0), only the limit."""
    clock = Clock()
    door = Door(draw=lambda: 0.5)
    door.fair = FairShares(clock=clock)
    arrive(door.fair, (("flood", 200), ("robot", 2)))
    clock.now += INTERVAL_S
    door.check_queue("cam", 47, 64, "flood")
    door.check_queue("cam", 48, 64, "flood")  # share 16/17: the flood's fair part is most of it
    for waiting in (56, 60, 63):
        with pytest.raises(ResourceExhausted, match=r"busy: camera cam has \d+ requests already waiting"):
            door.check_queue("cam", waiting, 64, "flood")
        door.check_queue("cam", waiting, 64, "robot")
    with pytest.raises(ResourceExhausted, match=r"has 64 requests already waiting for it \(limit 64\)") as exc:
        door.check_queue("cam", 64, 64, "robot")
    assert exc.value.retry_after_s == 0.1
    off = Door(0.0, draw=lambda: 0.99)
    off.check_queue("cam", 63, 64, "flood")
    with pytest.raises(ResourceExhausted):
        off.check_queue("cam", 64, 64, "robot")


def test_callers_past_the_tracked_number_share_one_part() -> None:
    """Spraying identities buys nothing: past max_callers, new callers count as one."""
    clock = Clock()
    fair = FairShares(clock=clock, max_callers=3)
    fair.arrived("robot")
    for k in range(100):
        fair.arrived(f"spray{k}")
    clock.now += INTERVAL_S
    assert fair.rate("robot") == pytest.approx(0.5)
    assert fair.admit("robot", 0.1) == 1.0
    assert fair.admit("spray99", 0.1) < 0.1  # one bucket for all of them, above the fair level


def test_the_door_refuses_a_flooding_caller_and_not_the_robot_beside_it() -> None:
    """The server's loop admits 20 %: the flooding caller is refused nearly always, the robot at
    its own modest rate never (without fairness both would be refused 80 % of the time)."""
    clock = Clock()
    draws = iter([0.5] * 10_000)
    door = Door(draw=lambda: next(draws))
    door.fair = FairShares(clock=clock)
    arrive(door.fair, (("flood", 90), ("robot", 3)))
    clock.now += INTERVAL_S
    door.loop.shedder.admit = 0.2
    door.check_server("robot")
    with pytest.raises(ResourceExhausted, match="the server is past its capacity"):
        door.check_server("flood")
    busy = Shedder(0.01)
    busy.admit = 0.2
    door.check_cameras([("cam", busy)], caller="robot")
    with pytest.raises(ResourceExhausted, match="camera cam is past what it can take now"):
        door.check_cameras([("cam", busy)], caller="flood")


def test_the_client_throttles_in_proportion_to_refusals_and_recovers() -> None:
    clock, draws = Clock(), iter([0.0] * 1000)
    throttle = AdaptiveThrottle(2.0, 10.0, clock=clock, draw=lambda: next(draws))
    for _ in range(100):  # all accepted: nothing held back
        throttle.check("r")
        throttle.accepted()
    assert throttle.reject_probability() == 0.0
    # A robot's first answer late or refused is no overload: nothing held back for a few refusals.
    fresh = AdaptiveThrottle(2.0, 10.0, clock=clock, draw=lambda: 0.0)
    for _ in range(MIN_EXCESS - 1):
        fresh.check("r")
    assert fresh.reject_probability() == 0.0 and fresh.refused_locally == 0
    # The server now takes 1 in 4: the client sends at most about twice what is accepted.
    sent = accepted = 0
    for i in range(400):
        try:
            throttle.check("r")
        except ResourceExhausted as exc:
            assert "client-side throttling" in str(exc) and exc.retry_after_s == 0
            continue
        sent += 1
        if i % 4 == 0:
            throttle.accepted()
            accepted += 1
    assert throttle.refused_locally == 400 - sent > 0
    assert throttle.reject_probability() > 0.3
    clock.now += 11.0  # a window later, with the refusals forgotten, everything goes again
    assert throttle.reject_probability() == 0.0
    assert AdaptiveThrottle(math.inf).reject_probability() == 0.0


@pytest.mark.parametrize("k", [0.5, float("nan"), "2"])
def test_a_bad_throttle_multiplier_is_refused(k: object) -> None:
    with pytest.raises(InvalidArgument, match="throttle_k"):
        AdaptiveThrottle(k)  # type: ignore[arg-type]
    with pytest.raises(InvalidArgument, match="throttle_k"):
        DrvsClient("127.0.0.1:1", throttle_k=k)  # type: ignore[arg-type]


# --- real processes -----------------------------------------------------------------------------


async def start_queueing_camera(server: str) -> ManagedProcess:
    """fault_roles.py's slow camera acknowledging each request 10 ms after the last: at most 100 a
    second, one at a time, and it reports at once."""
    camera = ManagedProcess(
        "queueing",
        [sys.executable, str(ROLES), "slow-camera", "--server", server, "--id", "queueing", *QUEUEING],
    )
    await camera.start()
    await camera.wait_for_line(r"^REGISTERED queueing", timeout=30)
    return camera


@contextlib.asynccontextmanager
async def beside_a_queueing_camera(*server_args: str) -> AsyncIterator[tuple[str, ManagedProcess]]:
    """A server (with `server_args`) and the queueing camera registered with it: the server's
    address and the camera; both stopped and reaped on exit."""
    server, address = await start_server(*server_args)
    try:
        camera = await start_queueing_camera(address)
        try:
            yield address, camera
        finally:
            await camera.stop()
    finally:
        await server.stop()


async def flood(robot: DrvsClient, seconds: float, tasks: int) -> tuple[list[str], list[tuple[str, float]], int]:
    """`tasks` loops asking about the queueing camera's region as fast as the answers come back, for
    `seconds`: the ids dispatched, the ids refused with how long their refusal took, the others."""
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    dispatched: list[str] = []
    refused: list[tuple[str, float]] = []
    other = 0

    async def one() -> None:
        nonlocal other
        while loop.time() < end:
            request_id = robot.new_request_id()
            started = time.perf_counter()
            try:
                sub = await robot.subscribe(YELLOW, QUEUED_REGION, request_id=request_id, timeout_s=2)
            except ResourceExhausted as exc:
                assert exc.retry_after_s > 0 or "client-side throttling" in str(exc), exc
                refused.append((request_id, time.perf_counter() - started))
                await asyncio.sleep(0)  # a refusal answers at once: let the others run
                continue
            except Exception:
                other += 1
                continue
            dispatched.append(request_id)
            sub.close()

    await asyncio.gather(*(one() for _ in range(tasks)))
    return dispatched, refused, other


@pytest.mark.slow
async def test_a_flooding_robot_is_shed_and_a_modest_one_beside_it_is_not() -> None:
    """Two robots on their own connections (their throttling off) ask the camera that takes 100
    requests a second: one floods it, one asks 10 times a second. The door sheds the flood's
    excess and leaves the modest robot's requests (nearly) alone. Without fair shares the door would draw
    for both alike, refusing most of the modest robot's requests as it refuses most of the flood;
    without the reserve at the end of the camera link's queue, the flood would fill it and the
    modest robot would be refused there.
    Meanwhile robots join, each on a new connection, and ask once: the door has not measured them,
    and admits them as the modest callers they are (before, it admitted a caller not yet measured
    only the flood's share, and refused most of them)."""
    async with (
        beside_a_queueing_camera("--rate-limit", "5000", "--max-forward-bytes", "1e10") as (address, _camera),
        DrvsClient(address, robot_id="flood", listen="127.0.0.1:0", throttle_k=math.inf) as flooder,
        DrvsClient(address, robot_id="modest", listen="127.0.0.1:0", throttle_k=math.inf) as modest,
    ):
        flooding = asyncio.ensure_future(flood(flooder, 6.0, 16))
        loop = asyncio.get_running_loop()
        start, asked, refused = loop.time() + 1.0, 0, 0  # its first second: the door learns the rates
        joiners: list[bool] = []  # each joiner's one request: refused?

        async def join() -> None:
            await asyncio.sleep(max(0.0, start - loop.time()))
            while loop.time() < start + 3.0:
                async with DrvsClient(address, robot_id="joiner", throttle_k=math.inf) as joiner:
                    paced = loop.time() + 0.25
                    try:
                        sub = await joiner.subscribe(YELLOW, QUEUED_REGION, timeout_s=2)
                    except ResourceExhausted:
                        joiners.append(True)
                    else:
                        joiners.append(False)
                        sub.close()
                await asyncio.sleep(max(0.0, paced - loop.time()))

        joining = asyncio.ensure_future(join())
        while (now := loop.time()) < start + 4.0:
            if now >= start:
                asked += 1
            try:
                sub = await modest.subscribe(YELLOW, QUEUED_REGION, timeout_s=2)
            except ResourceExhausted:
                refused += now >= start
            else:
                sub.close()
            await asyncio.sleep(max(0.0, now + 0.1 - loop.time()))  # its pace: 10 a second
        await joining
        dispatched, flood_refused, other = await flooding
    assert other == 0 and asked >= 20
    shed = len(flood_refused) / (len(flood_refused) + len(dispatched))
    assert shed > 0.5, (len(flood_refused), len(dispatched))
    # Fair: the modest robot is hardly ever refused (alike, both would lose about the flood's share).
    # Nor when the flood fills the camera's link (--max-queued-forwards): its last quarter is kept
    # for callers below their fair part (before, the link's limit refused the modest robot 25-55 %
    # of the time, whoever had filled it).
    assert refused <= asked // 10, (refused, asked, shed)
    assert len(joiners) >= 6 and sum(joiners) <= len(joiners) // 5, (joiners, shed)


@pytest.mark.slow
async def test_past_a_cameras_capacity_the_server_refuses_at_once_before_asking_it() -> None:
    """A robot (its own throttling off) floods a camera that takes 100 requests a second. The
    server refuses what the camera's standing queue cannot take: RESOURCE_EXHAUSTED with a retry
    hint, at once, and the camera never hears of a refused request. Once the flood ends the camera
    is asked again. Without the door every request would be queued for the camera, and none refused."""
    async with (
        beside_a_queueing_camera("--rate-limit", "5000", "--max-forward-bytes", "1e10") as (address, camera),
        DrvsClient(address, robot_id="flood", listen="127.0.0.1:0", throttle_k=math.inf) as robot,
    ):
        dispatched, refused, other = await flood(robot, 3.0, 16)
        assert other == 0
        assert len(refused) > len(dispatched) / 2, (len(refused), len(dispatched))
        # At once: far below the forward timeout (5 s), whatever this machine is doing.
        assert max(took for _, took in refused) < 1.0, max(took for _, took in refused)
        # Nothing refused was forwarded: the camera logs every request it is asked.
        asked = {m.group(1) for line in camera.lines if (m := re.match(r"^REQUEST (\S+)", line))}
        assert asked <= set(dispatched) and not asked & {r for r, _ in refused}
        # The flood is over: the queue drains and the camera is asked again.
        for _ in range(50):
            try:
                result = await robot.detect(YELLOW, QUEUED_REGION, timeout_s=5)
            except ResourceExhausted as exc:
                await asyncio.sleep(exc.retry_after_s)  # as the hint says
                continue
            assert result.finished_cameras == {"queueing"}
            break
        else:
            raise AssertionError("the camera was never asked again after the flood")


@pytest.mark.slow
async def test_a_robot_refused_for_overload_holds_back_its_own_requests() -> None:
    """The same flood from a robot with its default throttling: it refuses part of its own
    requests without sending them, so the server sees fewer than the robot's code made."""
    async with (
        beside_a_queueing_camera("--rate-limit", "5000", "--max-forward-bytes", "1e10") as (address, _),
        DrvsClient(address, robot_id="polite", listen="127.0.0.1:0") as robot,
    ):
        _, refused, other = await flood(robot, 3.0, 16)
        assert other == 0
        local = robot.throttle.refused_locally
        assert 0 < local <= len(refused), (local, len(refused))


@pytest.mark.slow
async def test_a_refused_fused_request_on_a_stream_is_told_so_at_once() -> None:
    """Fused single shots over the robot's rate budget on its request stream: each is refused at
    once with RESOURCE_EXHAUSTED naming it, the rest answered; none waits out its deadline. (The
    server renamed a fused request for the cameras before its last checks, and its refusal went
    out under that name: the robot never heard of it and timed out.)"""
    async with (
        beside_a_queueing_camera("--rate-limit", "2") as (address, _),
        DrvsClient(address, robot_id="eager", throttle_k=math.inf) as robot,
    ):

        async def ask() -> str:
            try:
                await robot.snapshot(YELLOW, QUEUED_REGION, deadline_s=0.3, timeout_s=2)
            except ResourceExhausted as exc:
                assert "rate" in str(exc), exc
                return "refused"
            return "answered"

        outcomes = await asyncio.gather(*(ask() for _ in range(12)))  # a DeadlineExceeded fails here
        assert outcomes.count("refused") >= 6 and "answered" in outcomes, outcomes
