"""drvs.tools.launch, which the demo, the office and most tests start their processes with: readiness is
awaited by gRPC health, and a process is never left running when a wait fails or times out."""

from __future__ import annotations

import asyncio
import sys

import pytest
from grpc import aio
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, running, running_server, start_camera, start_server, wait_serving
from tests.helpers import CAM1_REGION, YELLOW


def sleeper(seconds: float = 60) -> ManagedProcess:
    return ManagedProcess(
        "sleeper", [sys.executable, "-c", f"import time; print('up', flush=True); time.sleep({seconds})"]
    )


async def test_wait_that_times_out_kills_and_reaps_the_process() -> None:
    proc = await sleeper().start()
    await proc.wait_for_line("^up$", timeout=30)
    with pytest.raises(TimeoutError, match=r"sleeper did not exit within 0.2 s \(killed\)"):
        await proc.wait(timeout=0.2)
    assert proc.returncode is not None and proc.returncode < 0  # killed by a signal, and reaped
    assert proc not in running()


async def test_wait_that_is_cancelled_kills_and_reaps_the_process() -> None:
    proc = await sleeper().start()
    waiting = asyncio.ensure_future(proc.wait(timeout=60))
    await proc.wait_for_line("^up$", timeout=30)
    waiting.cancel()
    with pytest.raises(asyncio.CancelledError):
        await waiting
    assert proc.returncode is not None


async def test_context_manager_stops_the_process_when_the_body_fails() -> None:
    with pytest.raises(ZeroDivisionError):
        async with sleeper() as proc:
            await proc.wait_for_line("^up$", timeout=30)
            _ = 1 / 0
    assert proc.returncode is not None and proc not in running()


async def test_start_server_that_exits_fails_at_once_with_its_output() -> None:
    # RuntimeError, not TimeoutError: the exit itself ends the wait, not the (long) timeout.
    with pytest.raises(RuntimeError, match=r"server exited \(code 2\) before logging") as err:
        await start_server("--lease-ttl", "-1", timeout=600)
    # Its own complaint comes with it.
    assert "lease_ttl_s (--lease-ttl, DRVS_LEASE_TTL): -1 must be in (0, 3600]" in str(err.value)


async def test_start_server_that_times_out_is_reaped() -> None:
    before = running()
    with pytest.raises(TimeoutError, match="server: still no logging"):
        await start_server(timeout=0.05)
    assert running() == before  # nothing left behind


async def test_start_camera_returns_once_the_server_routes_to_it(recorded: dict[str, RecordedCamera]) -> None:
    rec = recorded["cam1"]
    async with running_server() as (_, address):
        camera = await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", "6")
        try:
            async with DrvsClient(address) as robot:
                assert [c.camera_id for c in await robot.cameras()] == ["cam1"]
                result = await robot.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert result.complete and [r.camera_id for r in result.reports] == ["cam1"]
        finally:
            assert await camera.stop() == 0


@pytest.mark.slow
async def test_start_camera_whose_server_never_answers_is_reaped(recorded: dict[str, RecordedCamera]) -> None:
    rec = recorded["cam1"]
    before = running()
    with pytest.raises(TimeoutError, match=r"cam1: still no logging '.*registered with' after"):
        await start_camera("cam1", rec.video, rec.homography_file, "127.0.0.1:1", "--max-range", "6", timeout=8)
    assert running() == before


async def test_wait_serving_waits_for_serving_by_the_health_watch() -> None:
    """A server whose health says NOT_SERVING: wait_serving does not return until it says SERVING."""
    server = aio.server()
    servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    address = f"127.0.0.1:{port}"
    try:
        await servicer.set("", health_pb2.HealthCheckResponse.NOT_SERVING)
        with pytest.raises(TimeoutError, match=rf"^{address}: still no gRPC health SERVING at {address} after 0.5 s"):
            await wait_serving(address, timeout=0.5)
        waiting = asyncio.ensure_future(wait_serving(address, timeout=30))
        await servicer.set("", health_pb2.HealthCheckResponse.SERVING)
        await asyncio.wait_for(waiting, 10)
    finally:
        await server.stop(0)
