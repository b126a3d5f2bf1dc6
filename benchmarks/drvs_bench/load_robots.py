"""drvs-bench load-robots: the load benchmark's worker process, N robots on an open-loop schedule
(drvs_bench.load starts these and reads what they write)."""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import time
from collections.abc import Callable, Coroutine, Sequence
from pathlib import Path
from typing import Any, TypeVar

import grpc

from drvs.core.errors import DrvsError, ResourceExhausted
from drvs.core.geometry import box_region
from drvs.robot import DetectionResult, DrvsClient, Snapshot
from drvs.robot.throttle import DEFAULT_K
from drvs.v1 import detection_pb2, detection_pb2_grpc
from drvs.wire import _grpc
from drvs.wire.convert import region_to_pb, snapshot_from_pb

from .common import ALL_REGION, YELLOW

CAMERAS = 3
R = TypeVar("R")
#: fused-unary: fused single shots as unary DetectObjects calls on a plain gRPC stub, one
#: connection per robot, as a client without DrvsClient (another language, grpcurl) sends them:
#: no request stream, no client-side throttle, the retry hint ignored.
DELIVERIES = ("per-camera", "fused", "fused-unary")
#: Outcomes of one request, in the order they are published.
OUTCOMES = ("complete", "refused_server", "refused_local", "incomplete", "lost")
#: A refusal's reason, from its message (diagnostics only: outcomes do not depend on it).
REFUSAL_REASONS = (
    ("client-side throttling", "client_throttle"),
    ("overloaded: the server", "server_loop"),
    ("overloaded: camera", "camera_link"),
    ("overloaded: fused delivery", "fused_delivery"),
    ("busy: camera", "camera_queue"),
    ("REFUSED_STREAM", "refused_stream"),
    ("dropped before it was taken in", "dropped_pending"),
)
#: The refusals that did not come as RESOURCE_EXHAUSTED on the wire (a fused-unary robot's raw
#: status: UNAVAILABLE REFUSED_STREAM, and CANCELLED from gRPC's queue of calls not taken in).
NOT_RESOURCE_EXHAUSTED = ("refused_stream", "dropped_pending")


# --- the worker process: N robots -----------------------------------------------------------------


def schedule(robot: int, robots: int, rate: float, end: float) -> list[float]:
    """A robot's send times, as offsets (s) from the start: robots spread evenly over one period,
    so the load is smooth, not all of them at once. The coordinator counts the work from it too."""
    phase = robot / robots / rate
    offsets = []
    k = 0
    while (offset := phase + k / rate) < end:
        offsets.append(offset)
        k += 1
    return offsets


def expected_requests(robots: int, rate: float, warmup: float, seconds: float) -> int:
    """Requests the robots must send after the warm-up: what the counts are checked against."""
    return sum(1 for g in range(robots) for o in schedule(g, robots, rate, warmup + seconds) if not o < warmup)


def refusal_reason(exc: ResourceExhausted) -> str:
    """What a refusal's message says refused it (REFUSAL_REASONS); `no_retry_hint` for one
    without a hint (a per-robot budget), `other` for the rest."""
    text = str(exc)
    for needle, reason in REFUSAL_REASONS:
        if needle in text:
            return reason
    return "no_retry_hint" if exc.retry_after_s == 0 else "other"


async def started(args: argparse.Namespace) -> float:
    """Say READY, wait for SIGUSR1, and return the start time the coordinator wrote into --go-file
    (its wall clock) on this loop's clock."""
    loop = asyncio.get_running_loop()
    go = asyncio.Event()
    loop.add_signal_handler(signal.SIGUSR1, go.set)
    print("READY", flush=True)
    await go.wait()
    start_wall = float(await asyncio.to_thread(Path(args.go_file).read_text))
    return loop.time() + (start_wall - time.time())


async def run_schedule(
    args: argparse.Namespace, start: float, robots: Sequence[R], one: Callable[[R, float], Coroutine[Any, Any, None]]
) -> tuple[float, float]:
    """Every robot's requests on its schedule from `start`, each `one(robot, offset)` in a task of its
    own (open loop), all awaited: this process's CPU seconds and the wall seconds from the end of
    the warm-up (it exits before the coordinator's last sample)."""
    loop = asyncio.get_running_loop()
    tasks: list[asyncio.Task[None]] = []
    cpu_at_warmup = [time.process_time()]
    loop.call_at(start + args.warmup, lambda: cpu_at_warmup.__setitem__(0, time.process_time()))

    async def robot(index: int, who: R) -> None:
        for offset in schedule(args.index_offset + index, args.total_robots, args.rate, args.warmup + args.seconds):
            delay = start + offset - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            tasks.append(loop.create_task(one(who, offset)))

    await asyncio.gather(*(robot(i, r) for i, r in enumerate(robots)))
    await asyncio.gather(*tasks)
    return time.process_time() - cpu_at_warmup[0], loop.time() - (start + args.warmup)


def classify_failure(record: list[Any], exc: DrvsError, elapsed_s: float, local: bool = False) -> None:
    """A request's record from the error it raised, `elapsed_s` after its scheduled send: a refusal
    (ResourceExhausted: by the server, or by the robot's own throttle when `local`) with its time and
    reason; anything else lost, by its kind."""
    record[5] = type(exc).__name__
    if isinstance(exc, ResourceExhausted):
        record[7] = "refused_local" if local else "refused_server"
        record[8] = round(elapsed_s * 1000, 2)
        record[9] = refusal_reason(exc)
    else:
        record[9] = record[5]


def classify_snapshot(record: list[Any], snapshot: Snapshot, elapsed_s: float) -> None:
    """A fused request's record from its snapshot, `elapsed_s` after its scheduled send."""
    missing = set(snapshot.camera_errors)
    record[2] = min(CAMERAS, len(set(snapshot.camera_ids) - missing))
    record[3] = len(snapshot.camera_errors)
    if not missing and len(snapshot.camera_ids) == CAMERAS:
        record[4] = round(elapsed_s * 1000, 2)
        record[7] = "complete"
    else:
        codes = sorted(m.code for m in snapshot.camera_errors.values())
        record[7] = "incomplete"
        record[9] = ",".join(codes) or f"merged_{len(snapshot.camera_ids)}_cameras"


async def robots_worker(args: argparse.Namespace) -> None:
    """`drvs-bench load-robots`: start N robots, say READY, wait for the start time in --go-file,
    run the schedule, print DONE with one record per request."""
    loop = asyncio.get_running_loop()
    if args.delivery == "fused-unary":
        await unary_worker(args)
        return
    fused = args.delivery == "fused"
    clients = [
        DrvsClient(
            args.server,
            robot_id=f"{args.name}-{i}",
            listen=None if fused else "127.0.0.1:0",  # a fused robot dials out only
            throttle_k=args.throttle_k,
        )
        for i in range(args.robots)
    ]
    for client in clients:
        await client.start()
    try:
        for client in clients:  # connections up, one round each
            if fused:
                await client.snapshot(YELLOW, ALL_REGION, timeout_s=10)
            else:
                await client.detect(YELLOW, ALL_REGION, timeout_s=10)
        start = await started(args)
        refused_locally_before = sum(c.throttle.refused_locally for c in clients)
        # Per request: [0] scheduled offset from the start (s), [1] lag of the send behind schedule
        # (ms), [2] final reports (fused: cameras merged) without error, [3] with error (fused:
        # missing cameras), [4] the latency from the scheduled send time to the last final report
        # or the snapshot (ms, or -1 unless complete), [5] the exception the request raised ("" if
        # none), [6] whether it was scheduled in the warm-up, [7] its outcome (OUTCOMES), [8] the
        # time from the scheduled send to a refusal (ms, or -1), [9] what: a refusal's reason, an
        # incomplete request's error codes (comma-separated, one per camera), a lost one's kind.
        records: list[list[Any]] = []

        def classify_result(record: list[Any], result: DetectionResult, scheduled: float) -> None:
            record[2] = sum(1 for r in result.reports if r.final and not r.error)
            record[3] = sum(1 for r in result.reports if r.final and r.error)
            if result.complete and len(result.camera_ids) == CAMERAS and record[2] == CAMERAS:
                record[4] = round((loop.time() - scheduled) * 1000, 2)
                record[7] = "complete"
            elif result.unfinished_cameras:  # a final report that never came (deadline, stream ended)
                record[7], record[9] = "lost", "missing_final_report"
            else:
                codes = sorted(e.code for e in result.camera_errors.values())
                record[7] = "incomplete"
                record[9] = ",".join(codes) or f"dispatched_to_{len(result.camera_ids)}_cameras"

        async def one(client: DrvsClient, offset: float) -> None:
            scheduled = start + offset
            sent = loop.time()
            record: list[Any] = [
                round(offset, 4),
                round((sent - scheduled) * 1000, 2),
                0,
                0,
                -1.0,
                "",
                offset < args.warmup,
                "lost",
                -1.0,
                "",
            ]
            records.append(record)
            # A local refusal is raised before the call's first await, so no other request of this
            # client can move the count in between; a server refusal carries a retry hint.
            refused_before = client.throttle.refused_locally
            try:
                if fused:
                    snapshot = await client.snapshot(YELLOW, ALL_REGION, timeout_s=args.timeout)
                else:
                    sub = await client.subscribe(YELLOW, ALL_REGION, timeout_s=args.timeout)
                    result = await sub.collect()
            except DrvsError as exc:
                hinted = isinstance(exc, ResourceExhausted) and exc.retry_after_s > 0
                local = client.throttle.refused_locally > refused_before and not hinted
                classify_failure(record, exc, loop.time() - scheduled, local)
                return
            if fused:
                classify_snapshot(record, snapshot, loop.time() - scheduled)
            else:
                classify_result(record, result, scheduled)

        cpu_s, wall_s = await run_schedule(args, start, clients, one)
        # The clients' own count of requests they refused over the whole schedule (warm-up included):
        # the coordinator checks the records' refused_local against it.
        refused_locally = sum(c.throttle.refused_locally for c in clients) - refused_locally_before
        done = {"records": records, "cpu_s": cpu_s, "wall_s": wall_s, "refused_locally": refused_locally}
        print("DONE " + json.dumps(done), flush=True)
    finally:
        for client in clients:
            await client.close()


class UnaryRobot:
    """A fused-unary robot: one channel (its own connection), DetectObjects with fusion."""

    def __init__(self, server: str, robot_id: str) -> None:
        self.robot_id = robot_id
        self.channel = _grpc.insecure_channel(server)
        self.stub = detection_pb2_grpc.DetectObjectBoundaryStub(self.channel)
        self.sent = 0
        self.region = region_to_pb(box_region(*ALL_REGION))

    async def snapshot(self, timeout_s: float) -> Snapshot:
        """One fused single shot; the failure as DrvsClient would raise it (drvs.wire._grpc)."""
        self.sent += 1
        message = detection_pb2.DetectionRequest(
            request_id=f"{self.robot_id}-{self.sent}", robot_id=self.robot_id, filter_def=YELLOW, region=self.region,
            fusion=detection_pb2.FusionOptions(compact_geometry=True),
        )  # fmt: skip
        try:
            reply = await self.stub.DetectObjects(message, timeout=timeout_s)
        except grpc.RpcError as exc:
            raise _grpc.from_rpc_error(exc, f"request {message.request_id}") from None
        if reply.HasField("error"):
            raise _grpc.error_from_code(reply.error.code, reply.error.message, reply.error.retry_after_s)
        return snapshot_from_pb(reply.snapshot, message.request_id)


async def unary_worker(args: argparse.Namespace) -> None:
    """robots_worker for --delivery fused-unary: the same schedule, records and outcomes."""
    loop = asyncio.get_running_loop()
    robots = [UnaryRobot(args.server, f"{args.name}-{i}") for i in range(args.robots)]
    try:
        for robot in robots:  # connections up, one round each
            await robot.snapshot(10)
        start = await started(args)
        records: list[list[Any]] = []

        async def one(robot: UnaryRobot, offset: float) -> None:
            scheduled = start + offset
            record: list[Any] = [round(offset, 4), round((loop.time() - scheduled) * 1000, 2), 0, 0, -1.0, "",
                                 offset < args.warmup, "lost", -1.0, ""]  # fmt: skip
            records.append(record)
            try:
                snapshot = await robot.snapshot(args.timeout)
            except DrvsError as exc:
                classify_failure(record, exc, loop.time() - scheduled)
                return
            classify_snapshot(record, snapshot, loop.time() - scheduled)

        cpu_s, wall_s = await run_schedule(args, start, robots, one)
        done = {"records": records, "cpu_s": cpu_s, "wall_s": wall_s, "refused_locally": 0}
        print("DONE " + json.dumps(done), flush=True)
    finally:
        for robot in robots:
            await robot.channel.close()


def add_worker_parser(sub: Any) -> None:
    w = sub.add_parser("load-robots", help="(internal) the load benchmark's robots, one worker process")
    w.add_argument("--server", required=True)
    w.add_argument("--name", required=True)
    w.add_argument("--robots", type=int, required=True)
    w.add_argument("--index-offset", type=int, default=0)
    w.add_argument("--total-robots", type=int, required=True)
    w.add_argument("--rate", type=float, required=True)
    w.add_argument("--warmup", type=float, required=True)
    w.add_argument("--seconds", type=float, required=True)
    w.add_argument("--timeout", type=float, required=True)
    w.add_argument("--go-file", required=True, help="holds the start time (time.time()) once SIGUSR1 arrives")
    w.add_argument("--delivery", choices=DELIVERIES, default="per-camera")
    w.add_argument("--throttle-k", type=float, default=DEFAULT_K, help="DrvsClient's throttle_k (inf: off)")
    w.set_defaults(func=lambda args: asyncio.run(robots_worker(args)) or 0)
