"""Scouts' poses from the simulated world: a mobile camera node's pose source
(`drvs-camera --pose-source sim://HOST:PORT/SCOUT_ID`, the `sim` plug-in of the
``drvs.pose_sources`` entry-point group), and the mover (`drvs-sim scout`) that plays a scout's
localisation: it follows the world's poses of one scout and serves them as the tcp:// newline-
delimited JSON feed a real robot would, optionally late and noisy by known amounts."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import random
from collections.abc import AsyncIterator

import grpc
from grpc import aio

from drvs.core.backoff import Backoff
from drvs.core.errors import DrvsError, InvalidArgument
from drvs.core.mobile import INITIAL_BACKOFF_S, MAX_BACKOFF_S, Push
from drvs.core.model import Pose2, check_id
from drvs.core.net import parse_address
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire import _grpc
from drvs.wire._cli import setup_logging, shutdown_event

log = logging.getLogger("drvs.sim.poses")
SCHEME = "sim://"
#: Poses a second asked of the world.
DEFAULT_RATE_HZ = 20.0


def parse_spec(spec: str) -> tuple[str, str]:
    """`sim://HOST:PORT/SCOUT_ID` -> (HOST:PORT, SCOUT_ID); InvalidArgument naming --pose-source."""
    rest = spec[len(SCHEME) :] if spec.startswith(SCHEME) else spec
    address, sep, scout_id = rest.partition("/")
    if not sep or not scout_id:
        raise InvalidArgument(f"--pose-source: {spec!r} names no scout; expected sim://HOST:PORT/SCOUT_ID")
    parse_address(address, "--pose-source")
    check_id(scout_id, "--pose-source scout id")
    return address, scout_id


async def scout_poses(world: str, scout_id: str, rate_hz: float) -> AsyncIterator[tuple[float, Pose2]]:
    """(time, pose) of a scout from the world at `rate_hz`, reconnecting with backoff when the
    world's stream breaks; NOT_FOUND (no such scout) ends it with InvalidArgument."""
    backoff = Backoff(INITIAL_BACKOFF_S, MAX_BACKOFF_S)
    while True:
        async with _grpc.insecure_channel(world) as channel:
            stub = sim_pb2_grpc.SimulatedWorldStub(channel)
            try:
                call = stub.WatchScout(
                    sim_pb2.WatchScoutRequest(scout_id=scout_id, rate_hz=rate_hz), wait_for_ready=True
                )
                async for p in call:
                    backoff.reset()
                    yield p.time_unix, Pose2(p.x, p.y, p.theta)
            except aio.AioRpcError as exc:
                if exc.code() in (grpc.StatusCode.NOT_FOUND, grpc.StatusCode.INVALID_ARGUMENT):
                    raise InvalidArgument(f"world {world}: {exc.details()}") from None
                log.warning(
                    "world %s: scout %s's poses: %s; again in %.1f s", world, scout_id, exc.code().name,
                    backoff.current,
                )  # fmt: skip
        await backoff.sleep()


class SimPoseSource:
    """A scout's poses straight from the world (`sim://HOST:PORT/SCOUT_ID`): its true pose, on time."""

    def __init__(self, spec: str) -> None:
        self.world, self.scout_id = parse_spec(spec)
        self.description = spec

    async def run(self, push: Push) -> None:
        async for t, pose in scout_poses(self.world, self.scout_id, DEFAULT_RATE_HZ):
            push(t, pose)


class Mover:
    """Serves one scout's poses as a tcp:// newline-delimited JSON feed (drvs.camera.poses), each
    `delay_s` late and off by Gaussian noise of `noise_m` (position, each axis) and `noise_deg`
    (heading), standard deviations: a robot's localisation, as good or as bad as asked."""

    def __init__(
        self,
        world: str,
        scout_id: str,
        listen: str = "127.0.0.1:0",
        *,
        rate_hz: float = DEFAULT_RATE_HZ,
        delay_s: float = 0.0,
        noise_m: float = 0.0,
        noise_deg: float = 0.0,
        seed: int = 0,
    ) -> None:
        parse_address(world, "--world")
        self.host, self.port = parse_address(listen, "--listen", allow_port_zero=True)
        check_id(scout_id, "--id")
        for name, value, lo, hi in (
            ("--rate-hz", rate_hz, 0.1, 200.0),
            ("--delay-s", delay_s, 0.0, 10.0),
            ("--noise-m", noise_m, 0.0, 10.0),
            ("--noise-deg", noise_deg, 0.0, 180.0),
        ):
            if not (math.isfinite(value) and lo <= value <= hi):
                raise InvalidArgument(f"{name}: {value:g} is not in [{lo:g}, {hi:g}]")
        if rate_hz <= 0:
            raise InvalidArgument("--rate-hz: must be positive")
        self.world, self.scout_id = world, scout_id
        self.rate_hz, self.delay_s, self.noise_m, self.noise_deg = rate_hz, delay_s, noise_m, noise_deg
        self._random = random.Random(seed)
        self._clients: set[asyncio.Queue[bytes]] = set()
        self._server: asyncio.Server | None = None
        self._follower: asyncio.Task[None] | None = None
        self.address = ""
        self.sent = 0

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, self.host, self.port)
        port = self._server.sockets[0].getsockname()[1]
        self.address = f"{self.host}:{port}"
        self._follower = asyncio.get_running_loop().create_task(self._follow())
        log.info("scout %s: pose feed on tcp://%s (from world %s)", self.scout_id, self.address, self.world)

    async def stop(self) -> None:
        if self._follower is not None:
            self._follower.cancel()
            with contextlib.suppress(asyncio.CancelledError, DrvsError):
                await self._follower
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    async def run_until(self, stop: asyncio.Event) -> None:
        """Serve until `stop` is set; the world's refusal (no such scout) is raised."""
        assert self._follower is not None, "start() first"
        stopping = asyncio.get_running_loop().create_task(stop.wait())
        try:
            await asyncio.wait([self._follower, stopping], return_when=asyncio.FIRST_COMPLETED)
        finally:
            stopping.cancel()
        if self._follower.done() and not self._follower.cancelled() and self._follower.exception() is not None:
            raise self._follower.exception()  # type: ignore[misc]

    def line(self, t: float, pose: Pose2) -> bytes:
        """The feed's line for the pose the world gave at `t`: noisy as configured."""
        g = self._random.gauss
        x = pose.x + (g(0.0, self.noise_m) if self.noise_m else 0.0)
        y = pose.y + (g(0.0, self.noise_m) if self.noise_m else 0.0)
        yaw = pose.yaw + (math.radians(g(0.0, self.noise_deg)) if self.noise_deg else 0.0)
        return (json.dumps({"t": t, "x": x, "y": y, "yaw": yaw}) + "\n").encode()

    async def _follow(self) -> None:
        loop = asyncio.get_running_loop()
        async for t, pose in scout_poses(self.world, self.scout_id, self.rate_hz):
            line = self.line(t, pose)
            if self.delay_s:
                loop.call_later(self.delay_s, self._send, line)
            else:
                self._send(line)

    def _send(self, line: bytes) -> None:
        self.sent += 1
        for queue in self._clients:
            if queue.full():
                queue.get_nowait()  # a slow reader gets the newest poses
            queue.put_nowait(line)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        queue: asyncio.Queue[bytes] = asyncio.Queue(maxsize=256)
        self._clients.add(queue)
        try:
            while True:
                writer.write(await queue.get())
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            self._clients.discard(queue)
            writer.close()


def add_scout_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", required=True, help="the simulated world, HOST:PORT")
    p.add_argument("--id", required=True, help="the scout (scouts[].id in the world's scenario)")
    p.add_argument("--listen", default="127.0.0.1:0", help="where to serve the tcp:// pose feed (default %(default)s)")
    p.add_argument("--rate-hz", type=float, default=DEFAULT_RATE_HZ, help="poses a second (default %(default)g)")
    p.add_argument("--delay-s", type=float, default=0.0, help="send each pose this late, seconds (default 0)")
    p.add_argument("--noise-m", type=float, default=0.0, help="position noise, metres (std dev per axis; default 0)")
    p.add_argument("--noise-deg", type=float, default=0.0, help="heading noise, degrees (std dev; default 0)")
    p.add_argument("--seed", type=int, default=0, help="the noise's seed")
    p.add_argument("--log-level", default=None)


async def _serve_scout(args: argparse.Namespace) -> int:
    stop = shutdown_event()
    mover = Mover(
        args.world, args.id, args.listen, rate_hz=args.rate_hz, delay_s=args.delay_s,
        noise_m=args.noise_m, noise_deg=args.noise_deg, seed=args.seed,
    )  # fmt: skip
    await mover.start()
    print(f"scout {args.id}: pose feed listening on tcp://{mover.address}", flush=True)
    try:
        await mover.run_until(stop)
    finally:
        await mover.stop()
    return 0


def scout_main(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    try:
        return asyncio.run(_serve_scout(args))
    except DrvsError as exc:
        log.error("%s", exc)
        return 2
