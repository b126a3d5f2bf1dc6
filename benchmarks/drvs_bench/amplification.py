"""Request amplification: bytes the server forwards to cameras per byte a robot sends it.

On DetectStream a robot leaves out a region that repeats the previous request's, so a request of a
few bytes can stand for a 1000-point region (about 20 kB) that the server forwards in full to every
camera that sees it. This measures it with real sockets: a real drvs-server process, cameras that
accept every request (gRPC servers behind counting TCP relays, so the bytes are the sockets'), and a
robot (DrvsClient, metered) that sends one large region and then asks again and again about it.

    python -m drvs_bench.amplification                       # the server's default budget
    python -m drvs_bench.amplification --server-arg=--max-forward-bytes=1e12   # effectively none

prints one JSON line: bytes the robot sent, bytes the cameras received, their ratio, and the
forwarded bytes a second.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
from collections.abc import Sequence
from typing import Any

from grpc import aio

from drvs.core.errors import DrvsError, ResourceExhausted
from drvs.tools.fakes import AckingCamera, register_message, serve_camera
from drvs.tools.launch import start_server
from drvs.tools.meter import CountingRelay, MeteredClient
from drvs.v1 import detection_pb2, registry_pb2_grpc

YELLOW = "hsv_014110130035225200"
# Every camera is fakes.register_message's, at the origin looking along +y: it sees about x -3.8..3.8,
# y 1.5..7.5.


def big_region(points: int = 1000) -> list[tuple[float, float]]:
    """A `points`-gon of radius 1.5 m inside every camera's field of view."""
    return [
        (1.5 * math.cos(2 * math.pi * i / points), 4.5 + 1.5 * math.sin(2 * math.pi * i / points))
        for i in range(points)
    ]


class _AcceptingCamera(AckingCamera):
    """Accepts every forwarded request and reports nothing: only the forwarded bytes matter."""

    def __init__(self, camera_id: str, read: asyncio.Event) -> None:
        super().__init__(camera_id)
        self.requests = 0
        self.read = read  # set whenever a camera has read a batch

    async def batch(self, requests: Sequence[detection_pb2.DetectionRequest]) -> None:
        self.requests += len(requests)
        self.read.set()


async def measure(
    server_args: Sequence[str] = (),
    *,
    cameras: int = 4,
    seconds: float = 3.0,
    rate_hz: float = 150.0,
    points: int = 1000,
) -> dict[str, Any]:
    server, address = await start_server(*server_args)
    servers: list[aio.Server] = []
    relays: list[CountingRelay] = []
    accepting: list[_AcceptingCamera] = []
    read = asyncio.Event()
    try:
        async with aio.insecure_channel(address) as channel:
            registry = registry_pb2_grpc.RegisterVisionServiceStub(channel)
            for i in range(cameras):
                accepting.append(_AcceptingCamera(f"acc{i}", read))
                grpc_server, camera_address = await serve_camera(accepting[-1])
                servers.append(grpc_server)
                relay = CountingRelay("127.0.0.1", int(camera_address.rsplit(":", 1)[1]))
                await relay.start()
                relays.append(relay)
                await registry.Register(
                    register_message(f"acc{i}", address=f"127.0.0.1:{relay.port}"),
                    timeout=5,
                )
        region = big_region(points)
        loop = asyncio.get_running_loop()
        accepted = refused = 0
        refusals: set[str] = set()
        async with MeteredClient(address, robot_id="amp", listen_host="127.0.0.1") as metered:
            assert metered.client is not None
            robot = metered.client
            start = loop.time()
            for n in range(round(seconds * rate_hz)):
                delay = start + n / rate_hz - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                try:
                    sub = await robot.subscribe(YELLOW, region, timeout_s=0.05)
                    accepted += len(sub.camera_ids) == cameras
                    sub.close()
                except ResourceExhausted as exc:
                    refused += 1
                    refusals.add(str(exc).split(":")[0])
                except DrvsError as exc:
                    refusals.add(f"{type(exc).__name__}: {exc}")
            elapsed = loop.time() - start

            # Every forward the server made has passed the relays once the cameras have read it.
            async def all_read() -> None:
                while sum(c.requests for c in accepting) < accepted * cameras:
                    read.clear()
                    await read.wait()

            await asyncio.wait_for(all_read(), 10.0)
            robot_sent = metered.payload_bytes()[1]
        forwarded = sum(r.to_target for r in relays)
        return {
            "server_args": list(server_args),
            "region_points": points,
            "cameras": cameras,
            "seconds": round(elapsed, 2),
            "requests_sent": accepted + refused,
            "requests_forwarded": accepted,
            "requests_refused": refused,
            "refusals": sorted(refusals),
            "robot_bytes_sent": robot_sent,
            "camera_bytes_received": forwarded,
            "forwarded_per_robot_byte": round(forwarded / max(1, robot_sent), 1),
            "forwarded_bytes_per_s": round(forwarded / elapsed),
        }
    finally:
        for relay in relays:
            await relay.close()
        for grpc_server in servers:
            await grpc_server.stop(0)
        await server.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m drvs_bench.amplification", description=__doc__.split("\n\n")[0])
    p.add_argument("--server-arg", action="append", default=[], help="a drvs-server argument (repeatable)")
    p.add_argument("--cameras", type=int, default=4)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--rate", type=float, default=150.0, help="requests a second (default 150)")
    p.add_argument("--points", type=int, default=1000, help="points in the region's polygon (default 1000)")
    args = p.parse_args(argv)
    result = asyncio.run(
        measure(args.server_arg, cameras=args.cameras, seconds=args.seconds, rate_hz=args.rate, points=args.points)
    )
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
