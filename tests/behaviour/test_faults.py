"""Faults, each with real processes on real sockets (issue 6): a camera killed mid-request, the server
restarted, robots whose report listener is unreachable or never reads, and a slow camera.

test_end_to_end.py already covers a camera killed before a request, re-registration after a clean
server restart and an unreachable server; these tests add what happens *during* each fault, and
how long recovery takes.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import logging
import os
import re
import signal
import socket
import statistics
import sys
import time
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from grpc import aio

from drvs.core.errors import Unavailable
from drvs.robot import DrvsClient, RetryPolicy
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc
from tests.fakes import start_recorded_camera
from tests.helpers import BOTH_REGION, CAM1_REGION, YELLOW, Office, start_office, stop_office

ROLES = Path(__file__).parents[1] / "fakes" / "fault_roles.py"
#: The lease in the killed-camera test (cameras heartbeat every third of it).
LEASE_S = 3.0
#: The slow camera sits at x = 40: it sees about x 36..44, y 1.5..7.5, which no real camera sees.
SLOW_REGION = (34.0, 0.0, 46.0, 10.0)
ALL_THREE_REGION = (-6.0, 0.0, 46.0, 10.0)


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for {pid}")


async def latencies_ms(robot: DrvsClient, region: Sequence[float], count: int) -> list[float]:
    """Back-to-back single-shot requests: milliseconds from sending to every camera's final report."""
    loop = asyncio.get_running_loop()
    out = []
    for _ in range(count):
        t0 = loop.time()
        result = await robot.detect(YELLOW, region, timeout_s=5)
        assert result.complete and not result.errors, result
        out.append((loop.time() - t0) * 1000)
    return out


def log_time(line: str) -> float:
    """The timestamp at the start of a DRVS log line (text format), in seconds."""
    stamp = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")
    return stamp.timestamp()


def p90(values: list[float]) -> float:
    return sorted(values)[int(0.9 * (len(values) - 1))]


# --- a camera killed mid-request -----------------------------------------------------------------


@pytest.mark.slow
async def test_camera_killed_mid_request_does_not_cost_the_robot_the_other_cameras_reports(
    recorded: dict[str, RecordedCamera],
) -> None:
    # A lease of its own, longer than the office fixture's: the camera that stays up must not drop
    # out of routing when a busy machine delays one of its heartbeats.
    office = await start_office(recorded, lease_ttl=LEASE_S)
    try:
        await _killed_mid_request(office)
    finally:
        await stop_office(office)


async def _killed_mid_request(office: Office) -> None:
    cam2 = office.cameras["cam2"]
    loop = asyncio.get_running_loop()
    async with DrvsClient(office.address, robot_id="r1") as robot:
        # 10 Hz for 2 s: 21 reports from each camera; cam2 dies after its third.
        sub = await robot.subscribe(YELLOW, BOTH_REGION, rate_hz=10, duration_s=2.0, timeout_s=1.0)
        assert sorted(sub.camera_ids) == ["cam1", "cam2"]
        leaving: asyncio.Task[re.Match[str]] | None = None
        killed_at = 0.0
        async for report in sub:
            if report.camera_id == "cam2" and report.sequence == 2:
                log_from = len(office.server.lines)
                cam2.kill()  # SIGKILL: no deregistration, no goodbye on its report stream
                killed_at = time.time()
                # Out of routing when its lease runs out: at most one lease after its last heartbeat.
                leaving = loop.create_task(
                    office.server.wait_for_line(
                        r"camera cam2 left routing: lease expired", timeout=2 * LEASE_S + 2, start=log_from
                    )
                )
        assert leaving is not None, "cam2 never sent its third report"
        await cam2.wait()
        result = sub.result
        cam1 = [r for r in result.reports if r.camera_id == "cam1"]
        assert [r.sequence for r in cam1] == list(range(21))
        assert cam1[-1].final and all(len(r.detections) == 2 and not r.error for r in cam1)
        assert result.missing_cameras == {"cam2"}

        # Timed by the server's own log, so the test process's scheduling does not count.
        gone_after = log_time((await leaving).string) - killed_at
        # The lease runs out at most LEASE_S after the kill, and the server's sweep finds it within
        # one sweep period (a quarter of the lease) after that.
        assert gone_after <= LEASE_S + LEASE_S / 4 + 0.3, f"cam2 left routing {gone_after:.2f} s after it was killed"
        assert await _routes_only(robot, ["cam1"])
        after = await robot.detect(YELLOW, BOTH_REGION, timeout_s=5)
        assert after.camera_ids == ("cam1",) and len(after.detections) == 2
        # Out of routing but not forgotten: the answer says cam2's floor went unseen.
        assert after.missing_cameras == {"cam2"} and after.uncovered


class _Counting(logging.Handler):
    """Sets `reached` once `count` records containing `text` have been logged."""

    def __init__(self, text: str, count: int) -> None:
        super().__init__()
        self.text, self.count, self.seen = text, count, 0
        self.reached = asyncio.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage():
            self.seen += 1
            if self.seen >= self.count:
                self.reached.set()


async def _routes_only(robot: DrvsClient, camera_ids: list[str]) -> bool:
    return [c.camera_id for c in await robot.cameras()] == camera_ids


# --- the server restarted ------------------------------------------------------------------------

HEARTBEAT_S = 1.0
#: The longest a camera's channel waits between attempts to reach a server that went away
#: (drvs.wire._grpc's grpc.max_reconnect_backoff_ms, 2 s, plus gRPC's 20 % jitter): a camera's next
#: heartbeat after the restart may first wait out one such attempt.
RECONNECT_S = 2.4


@pytest.mark.slow
@pytest.mark.timeout(180)  # its own waits (starts, runs, requests) add up to 150 s
async def test_server_restart_fails_fast_retries_and_cameras_return_within_a_heartbeat_and_a_reconnect(
    recorded: dict[str, RecordedCamera], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="drvs.robot")
    server, address = await start_server("--lease-ttl", "4")
    procs: list[ManagedProcess] = [server]
    loop = asyncio.get_running_loop()
    try:
        for camera_id, rec in recorded.items():
            procs.append(await start_recorded_camera(camera_id, rec, address, "--heartbeat", str(HEARTBEAT_S)))
        cameras = procs[1:]
        async with (
            DrvsClient(address, robot_id="plain") as plain,
            DrvsClient(address, robot_id="patient", retry=RetryPolicy(attempts=9, initial_backoff_s=0.2)) as patient,
        ):
            assert (await plain.detect(YELLOW, BOTH_REGION, timeout_s=5)).complete
            assert (await patient.detect(YELLOW, BOTH_REGION, timeout_s=5)).complete

            server.kill()  # a crash
            await server.wait()
            # Every call during the outage fails fast, on the old stream and on new ones alike.
            for _ in range(3):
                t0 = loop.time()
                with pytest.raises(Unavailable):
                    await plain.detect(YELLOW, BOTH_REGION, timeout_s=5)
                assert loop.time() - t0 < 2.0, f"took {loop.time() - t0:.2f} s to fail"

            # A client asked to retry keeps trying with backoff, and gets through once the server is back.
            retries = _Counting("retrying", 4)
            logging.getLogger("drvs.robot").addHandler(retries)
            try:
                patient_call = loop.create_task(patient.detect(YELLOW, BOTH_REGION, timeout_s=5))
                await asyncio.wait_for(retries.reached.wait(), 10)  # the patient client retries
            finally:
                logging.getLogger("drvs.robot").removeHandler(retries)
            assert not patient_call.done()

            port = address.rsplit(":", 1)[1]
            lines = [len(p.lines) for p in cameras]
            server, again = await start_server("--lease-ttl", "4", "--listen", f"127.0.0.1:{port}")
            procs[0] = server
            assert again == address
            for proc, start in zip(cameras, lines, strict=True):
                await proc.wait_for_line(rf"camera {proc.name} re-registered", timeout=10, start=start)
            # Timed by the new server's own log, so the test process's scheduling does not count.
            up_at = log_time((await server.wait_for_line(r"drvs-server listening on")).string)
            back = {
                proc.name: log_time((await server.wait_for_line(rf"camera {proc.name} registered at")).string) - up_at
                for proc in cameras
            }
            assert max(back.values()) <= HEARTBEAT_S + RECONNECT_S + 0.5, f"back in routing after {back} s"

            outcome = await asyncio.wait_for(patient_call, 15)
            assert outcome.request_id
            # (A client without retries may still fail fast for a moment: its channel backs off
            # between connection attempts for up to 2 s.)
            after = await patient.detect(YELLOW, BOTH_REGION, timeout_s=5)
            assert sorted(after.camera_ids) == ["cam1", "cam2"] and after.complete and len(after.detections) == 4
    finally:
        for proc in reversed(procs):
            await proc.stop()


# --- a robot whose report listener is unreachable or never reads -----------------------------------


class _NeverReads(detection_pb2_grpc.CallbackCoordinatesServicer):
    """A robot listener that accepts each report stream and never reads from it."""

    def __init__(self) -> None:
        self.streams = 0
        self.release = asyncio.Event()

    async def ReportDetections(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionReport],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.ReportControl]:
        self.streams += 1
        await self.release.wait()
        return
        yield  # an (empty) async generator: the stream stays open until released


@contextlib.asynccontextmanager
async def unhelpful_listeners() -> AsyncIterator[dict[str, str]]:
    """Three callback addresses no report gets through to: a gRPC listener that never reads, a TCP
    socket that accepts and never answers, and a bound port where nothing listens."""
    never_reads = _NeverReads()
    grpc_server = aio.server(options=[("grpc.http2.bdp_probe", 0)])
    detection_pb2_grpc.add_CallbackCoordinatesServicer_to_server(never_reads, grpc_server)
    port = grpc_server.add_insecure_port("127.0.0.1:0")
    await grpc_server.start()
    held: list[asyncio.StreamWriter] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        held.append(writer)  # accept, then neither read nor write

    black_hole = await asyncio.start_server(hold, "127.0.0.1", 0)
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))  # bound, never listening: connections are refused
    try:
        yield {
            "never-reads": f"127.0.0.1:{port}",
            "black-hole": f"127.0.0.1:{black_hole.sockets[0].getsockname()[1]}",
            "refused": f"127.0.0.1:{closed.getsockname()[1]}",
        }
    finally:
        never_reads.release.set()
        await grpc_server.stop(0)
        for writer in held:
            writer.close()
        black_hole.close()
        await black_hole.wait_closed()
        closed.close()


@pytest.mark.slow
@pytest.mark.timeout(170)  # its own waits (starts, runs, requests) add up to 140 s
async def test_unreachable_or_stuck_robot_listeners_cost_nobody_else(office: Office) -> None:
    loop = asyncio.get_running_loop()
    cameras = list(office.cameras.values())
    async with DrvsClient(office.address, robot_id="good") as good:
        await latencies_ms(good, BOTH_REGION, 5)  # warm up
        baseline = await latencies_ms(good, BOTH_REGION, 30)

        # A real robot process that freezes (SIGSTOP) while both cameras stream to it at 100 Hz.
        frozen = ManagedProcess.entry_point(
            "frozen", "drvs-robot", "detect", "--server", office.address, "--filter", YELLOW, "--json",
            "--roi", ",".join(map(str, BOTH_REGION)), "--rate", "100", "--duration", "30", "--robot-id", "frozen",
        )  # fmt: skip
        await frozen.start()
        async with unhelpful_listeners() as listeners:
            bad = {kind: DrvsClient(office.address, robot_id=kind, advertise=a) for kind, a in listeners.items()}
            watchers: list[asyncio.Task[re.Match[str]]] = []
            try:
                await frozen.wait_for_line(r'"camera_id": "cam2"', timeout=30)
                os.kill(frozen.pid, signal.SIGSTOP)
                for client in bad.values():
                    await client.start()

                async def flood(seconds: float) -> None:
                    """Each robot: a continuous request at 20 Hz over both cameras, and single shots
                    at 20 Hz, whose reports can go nowhere."""
                    for client in bad.values():
                        await client.subscribe(YELLOW, BOTH_REGION, rate_hz=20, duration_s=seconds)
                    end = loop.time() + seconds
                    while loop.time() < end:
                        for client in bad.values():
                            await client.subscribe(YELLOW, BOTH_REGION)
                        await asyncio.sleep(0.05)

                # Every camera gives up on every one of them within a bounded time: the refused and
                # black-hole addresses at once, the frozen robot and the never-reading listener once
                # their 64 kB flow-control window is full (about 3 s at 40 reports a second) plus
                # the cameras' 5 s write timeout.
                gave_up = {
                    "frozen": r"callback 127\.0\.0\.1:\d+: robot did not take a report within 5 s",
                    "never-reads": rf"callback {re.escape(listeners['never-reads'])}: robot did not take a report",
                    "black-hole": rf"callback {re.escape(listeners['black-hole'])}: UNAVAILABLE",
                    "refused": rf"callback {re.escape(listeners['refused'])}: UNAVAILABLE",
                }
                watchers.extend(
                    loop.create_task(proc.wait_for_line(pattern, timeout=12.0))
                    for proc in cameras
                    for pattern in gave_up.values()
                )
                await flood(2.0)
                rss0 = [rss_bytes(p.pid) for p in cameras]
                flooding = loop.create_task(flood(8.0))
                during = await latencies_ms(good, BOTH_REGION, 30)
                await flooding
                rss1 = [rss_bytes(p.pid) for p in cameras]
                await asyncio.gather(*watchers)
            finally:
                for watcher in watchers:
                    watcher.cancel()
                await asyncio.gather(*watchers, return_exceptions=True)
                for client in bad.values():
                    await client.close()
                if frozen.returncode is None:
                    os.kill(frozen.pid, signal.SIGCONT)
                await frozen.stop()

        # The good robot's requests took about as long while the others' reports went nowhere.
        assert statistics.median(during) <= 2 * statistics.median(baseline) + 10, (baseline, during)
        for before, after in zip(rss0, rss1, strict=True):
            assert after - before < 30 * 2**20, f"camera RSS grew {(after - before) / 2**20:.1f} MB"
        after_flood = await latencies_ms(good, BOTH_REGION, 10)
        assert statistics.median(after_flood) <= 2 * statistics.median(baseline) + 10


# --- a slow camera -------------------------------------------------------------------------------


def slow_camera(server: str, *args: str) -> ManagedProcess:
    return ManagedProcess("slow", [sys.executable, str(ROLES), "slow-camera", "--server", server, *args])


@contextlib.asynccontextmanager
async def beside_a_slow_camera(
    office: Office, *args: str
) -> AsyncIterator[tuple[ManagedProcess, DrvsClient, DrvsClient, list[float]]]:
    """A slow camera (fault_roles.py slow-camera with `args`) registered in the office, and two
    robots: the first warmed up, with its baseline latencies (ms) on cam1 alone; the second idle."""
    slow = await slow_camera(office.address, *args).start()
    try:
        await slow.wait_for_line(r"^REGISTERED slow", timeout=30)
        async with (
            DrvsClient(office.address, robot_id="r1") as robot,
            DrvsClient(office.address, robot_id="r2") as other,
        ):
            await latencies_ms(robot, CAM1_REGION, 5)
            yield slow, robot, other, await latencies_ms(robot, CAM1_REGION, 30)
    finally:
        await slow.stop()


@pytest.mark.slow
@pytest.mark.timeout(170)  # its own waits (starts, runs, requests) add up to 140 s
async def test_a_slow_camera_delays_nobody_else(office: Office) -> None:
    """A camera whose detection takes three seconds: it accepts each request at once, and reports late."""
    loop = asyncio.get_running_loop()
    async with beside_a_slow_camera(office, "--report-delay", "3") as (_, robot, other, baseline):
        # Keep the slow camera busy: a dozen requests that each take it three seconds.
        t0 = loop.time()
        waiting = [await other.subscribe(YELLOW, SLOW_REGION, timeout_s=6) for _ in range(12)]
        assert all(s.camera_ids == ("slow",) for s in waiting)
        during = await latencies_ms(robot, CAM1_REGION, 30)
        # A request that also covers the slow camera: the others' reports come at once.
        sub = await robot.subscribe(YELLOW, ALL_THREE_REGION, timeout_s=6)
        assert sorted(sub.camera_ids) == ["cam1", "cam2", "slow"]
        t_sub = loop.time()
        arrivals = {}
        async for report in sub:
            arrivals[report.camera_id] = loop.time() - t_sub
        assert sub.result.complete and not sub.result.errors
        # Not held back by the slow camera: held, they would come with its report, 3 s late. (A
        # bound near the unloaded latency, 3 x p90 + 20 ms, failed once in CI on a busy machine at
        # 40 ms; the benchmarks measure how fast, this checks that nobody waits for the slow one.)
        assert max(arrivals["cam1"], arrivals["cam2"]) <= 1.0, arrivals
        assert arrivals["slow"] >= 2.5, arrivals
        results = [await s.collect() for s in waiting]
        assert all(r.complete and r.reports[0].camera_id == "slow" for r in results)
        assert loop.time() - t0 >= 3.0
    assert statistics.median(during) <= 1.5 * statistics.median(baseline) + 5, (baseline, during)


@pytest.mark.slow
@pytest.mark.timeout(170)  # its own waits (starts, runs, requests) add up to 140 s
async def test_a_camera_slow_to_accept_is_answered_for_and_delays_nobody_else(office: Office) -> None:
    """A camera that takes five seconds to accept a request: the server gives up on it after its
    forward timeout (2 s), answers the robot for it, and nobody else waits."""
    loop = asyncio.get_running_loop()
    accepts_late = ("--accept-delay", "5", "--report-delay", "0")
    async with beside_a_slow_camera(office, *accepts_late) as (slow, robot, other, baseline):
        sub = await other.subscribe(YELLOW, ALL_THREE_REGION, timeout_s=6)
        assert sorted(sub.camera_ids) == ["cam1", "cam2", "slow"]
        t_sub = loop.time()
        during = await latencies_ms(robot, CAM1_REGION, 30)
        arrivals = {}
        async for report in sub:
            arrivals[report.camera_id] = loop.time() - t_sub
        by_camera = {r.camera_id: r for r in sub.result.reports}
        assert not sub.result.complete and sub.result.camera_errors["slow"].code == "UNAVAILABLE"
        assert not by_camera["cam1"].error and not by_camera["cam2"].error
        # A timeout is not told apart from a closed port (drvs.server.routing_errors): one opaque UNAVAILABLE.
        assert "slow did not accept the request: UNAVAILABLE the server could not reach it" in by_camera["slow"].error
        assert 1.8 <= arrivals["slow"] <= 3.0, arrivals
        await slow.wait_for_line(rf"^REQUEST {sub.request_id}$", timeout=5)
    assert statistics.median(during) <= 1.5 * statistics.median(baseline) + 5, (baseline, during)
