"""A camera's address is whatever its registration says, and the server dials it: what fails on that
hop must not tell a robot whether a port is open or what listens there (drvs.server.routing_errors)."""

from __future__ import annotations

import asyncio
import logging
import re
import socket
from collections.abc import AsyncIterator

import pytest
from grpc import aio

from drvs.core.errors import DeadlineExceeded, InvalidArgument, Unavailable
from drvs.robot import DrvsClient
from drvs.server.routing_errors import RoutingErrors
from drvs.tools.launch import start_server
from drvs.v1 import registry_pb2_grpc
from tests.helpers import YELLOW, CapturingCamera, register_message, serving_detection

# Cameras 20 m apart, each seeing about x-3.8..x+3.8, y 1.5..6; one region meets all three.
CAMERAS = {"closed": 0.0, "http1": 20.0, "silent": 40.0}
ALL_THREE = (-1.0, 2.0, 41.0, 4.0)


async def _http1(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    await reader.read(1024)
    writer.write(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
    await writer.drain()
    writer.close()


@pytest.fixture
async def addresses() -> AsyncIterator[dict[str, str]]:
    """(a) a port nothing listens on (bound, never listening: refused), (b) an HTTP/1.1 server, (c) a
    listener that takes connections and never answers (the kernel's backlog, never accepted)."""
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(16)
    http1 = await asyncio.start_server(_http1, "127.0.0.1", 0)
    try:
        yield {
            "closed": f"127.0.0.1:{closed.getsockname()[1]}",
            "http1": f"127.0.0.1:{http1.sockets[0].getsockname()[1]}",
            "silent": f"127.0.0.1:{silent.getsockname()[1]}",
        }
    finally:
        http1.close()
        await http1.wait_closed()
        closed.close()
        silent.close()


async def test_a_robot_hears_one_opaque_unavailable_whatever_listens_at_a_cameras_address(
    addresses: dict[str, str],
) -> None:
    server, address = await start_server("--forward-timeout", "1")
    try:
        async with (
            aio.insecure_channel(address) as channel,
            DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot,
        ):
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            for camera_id, x in CAMERAS.items():
                await registry.Register(register_message(camera_id, x, addresses[camera_id]))
            ports = [a.rsplit(":", 1)[1] for a in addresses.values()]
            for attempt in ("forwarded", "skipped"):
                result = await robot.detect(YELLOW, ALL_THREE, timeout_s=5)
                errors = result.camera_errors
                assert set(errors) == set(CAMERAS), (attempt, errors)
                said = {(e.code, e.message.replace(camera_id, "ID")) for camera_id, e in errors.items()}
                assert len(said) == 1, (attempt, errors)  # the same words for all three
                code, message = said.pop()
                assert code == "UNAVAILABLE", (attempt, errors)
                for leak in ("refused", "http", "deadline", "127.0.0.1", *ports):
                    assert leak not in message.lower(), (attempt, leak, message)
            # The server's own log keeps what happened, for its operator.
            await server.wait_for_line(rf"camera closed could not be reached: UNAVAILABLE .*{ports[0]}", timeout=5)
            await server.wait_for_line(r"camera http1 could not be reached: UNAVAILABLE .*http1\.x", timeout=5)
            silent = r"camera silent could not be reached: DEADLINE_EXCEEDED .*no reply within 1 s"
            await server.wait_for_line(silent, timeout=5)
    finally:
        await server.stop()
    assert not [line for line in server.lines if re.search(r"Traceback", line)]


def test_the_details_are_logged_once_per_camera_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    """A camera that keeps failing costs the log one line per interval (and the count of the rest);
    what the camera itself said about the request reaches the robot unchanged."""
    errors = RoutingErrors(every_s=3600)
    with caplog.at_level(logging.WARNING, logger="drvs.server"):
        for i in range(5):
            said = errors.for_robot("cam", Unavailable(f"camera at 10.0.0.9:22: Connection refused ({i})"), "r")
            assert said == ("UNAVAILABLE", "the server could not reach it")
        errors.for_robot("other", DeadlineExceeded("camera at 10.0.0.8:80: no reply within 2 s"), "r")
        kept = errors.for_robot("cam", InvalidArgument("filter_def: camera cam does not serve 'x'"), "r")
    assert kept == ("INVALID_ARGUMENT", "filter_def: camera cam does not serve 'x'")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "Connection refused (0)" in lines[0] and "no reply within 2 s" in lines[1], lines


async def test_a_camera_slow_to_connect_is_reached_not_skipped() -> None:
    """A camera whose connection takes 0.6 s to set up (a loaded host, a slow link) gets its
    request, and stays in routing: a connection attempt has CONNECT_ATTEMPT_S to hear the camera's
    HTTP/2 SETTINGS, not gRPC's 200 ms that DRVS once set by accident (the forward failed at once,
    and the server skipped the camera until its next heartbeat)."""
    camera = CapturingCamera()
    relayed: list[asyncio.Task[None]] = []

    async def pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        finally:
            writer.close()

    async with serving_detection(camera) as upstream:
        host, port = upstream.rsplit(":", 1)

        async def slow(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await asyncio.sleep(0.6)  # the slow link under test, not synchronisation
            up_reader, up_writer = await asyncio.open_connection(host, int(port))
            relayed.extend([asyncio.create_task(pipe(reader, up_writer)), asyncio.create_task(pipe(up_reader, writer))])

        relay = await asyncio.start_server(slow, "127.0.0.1", 0)
        relay_address = f"127.0.0.1:{relay.sockets[0].getsockname()[1]}"
        server, address = await start_server()
        try:
            async with (
                aio.insecure_channel(address) as channel,
                DrvsClient(address, robot_id="r", listen="127.0.0.1:0") as robot,
            ):
                await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(
                    register_message("slow", 0.0, relay_address)
                )
                for attempt in range(2):
                    task = asyncio.create_task(robot.detect(YELLOW, (-1.0, 2.0, 1.0, 4.0), timeout_s=1))
                    forwarded = await asyncio.wait_for(camera.requests.get(), 10)
                    assert forwarded.filter_def == YELLOW, attempt
                    task.cancel()
                    await asyncio.gather(task, return_exceptions=True)
        finally:
            await server.stop()
            relay.close()
            for t in relayed:
                t.cancel()
            await asyncio.gather(*relayed, return_exceptions=True)
    assert not [line for line in server.lines if "could not be reached" in line], server.lines[-5:]
