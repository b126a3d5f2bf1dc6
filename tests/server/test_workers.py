"""drvs-server --workers N: N real server processes on one port (SO_REUSEPORT), sharing one real etcd.
Robots and cameras do not care which worker answers; a killed worker is started again; SIGTERM
stops them all."""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
from pathlib import Path

import pytest

from drvs.core.errors import ResourceExhausted
from drvs.robot import DrvsClient, RetryPolicy
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import SERVER_READY, ManagedProcess, start_camera, start_etcd, start_server
from tests.helpers import CAM1_REGION, MAX_RANGE, YELLOW, scrape

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"),
]

#: Robots, each on its own connection: the kernel spreads connections over the workers, and 16 of
#: them all landing on one of two workers is a chance of one in 32 768.
ROBOTS = 16
DISPATCHED = 'drvs_requests_total{outcome="dispatched"}'


async def ask(robot: DrvsClient) -> None:
    """A fused and a per-camera request: each sees cam1's two yellow discs. Sixteen robots at once
    on a busy machine may find cam1 past what it takes: a robot then waits as the hint says."""
    for fused in (True, False):
        for _ in range(20):
            try:
                if fused:
                    snapshot = await robot.snapshot(YELLOW, CAM1_REGION, timeout_s=10)
                    assert len(snapshot.objects) == 2 and not snapshot.camera_errors, snapshot
                else:
                    result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
                    assert result.complete and len(result.detections) == 2, result
            except ResourceExhausted as exc:
                await asyncio.sleep(exc.retry_after_s or 0.1)
                continue
            break
        else:
            raise AssertionError(f"{robot.robot_id}: refused 20 times for overload")


async def test_workers_share_one_port_and_the_registry(tmp_path: Path, recorded: dict[str, RecordedCamera]) -> None:
    etcd = await start_etcd(tmp_path)
    procs: list[ManagedProcess] = []
    try:
        server, address = await start_server(
            "--workers", "2", "--registry", "etcd://" + etcd[0].address, "--metrics-port", "0"
        )
        procs.append(server)
        # Two workers, one address; each its own metrics port and its own port for fused reports.
        listening = await server.wait_for_lines(SERVER_READY, 2, 30)
        assert {m.group(1) for m in listening} == {address}
        metrics = await server.wait_for_lines(r"metrics on http://127\.0\.0\.1:(\d+)/", 2, 30)
        ports = sorted({int(m.group(1)) for m in metrics})
        assert len(ports) == 2
        rec = recorded["cam1"]
        procs.append(await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE))
        # Registered through one worker, routed by both (each robot's connection lands on either).
        robots = [DrvsClient(address, robot_id=f"r{i}", retry=RetryPolicy.retries(3)) for i in range(ROBOTS)]
        try:
            for robot in robots:
                await robot.start()
            await asyncio.gather(*(ask(robot) for robot in robots))
            counts = [(await scrape(port)).get(DISPATCHED, 0.0) for port in ports]
            assert all(count > 0 for count in counts), counts
            assert sum(counts) >= 2 * ROBOTS, counts
            # A worker killed: it is started again, and the robots carry on through the port.
            (first,) = await server.wait_for_lines(r"worker 0 started \(pid (\d+)\)", 1, 5)
            start = len(server.lines)
            os.kill(int(first.group(1)), signal.SIGKILL)
            await server.wait_for_line(r"worker 0 \(pid \d+\) exited with -9; starting it again", 10, start)
            await server.wait_for_line(SERVER_READY, 30, start)
            await asyncio.gather(*(ask(robot) for robot in robots))
        finally:
            for robot in robots:
                await robot.close()
        # SIGTERM stops every worker, each draining as a single server does; the camera first.
        await procs.pop().stop()
        await server.stop()
        assert server.returncode == 0, server.output()
        assert sum("drvs-server stopped" in line for line in server.lines) == 2, server.output()
    finally:
        for proc in reversed(procs):
            await proc.stop()
        for member in etcd:
            await member.stop()
