"""drvs-ros2: a fused DRVS track on ROS 2 topics (docs/ros2.md).

    drvs-ros2 --server HOST:PORT[,...] --filter FILTER --region X0,Y0,X1,Y1 [--rate HZ]
              [--frame-id map] [--domain-id N] [--topic-prefix /drvs] [--qos reliable|sensor]
              [--height TYPE=M ...] [--use-sim-time]

Exit codes: 0 stopped (SIGINT/SIGTERM, or --duration over); 2 bad arguments, a request the
server refused (the message names what) or a DDS configuration Cyclone refuses (CYCLONEDDS_URI);
4 no server answers (or the track was lost before its first snapshot); 130 interrupted while
starting.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import re
import sys

from cyclonedds.core import DDSException

from drvs.core.errors import DrvsError, InvalidArgument, Unavailable
from drvs.core.model import DEFAULT_FRAME, MAX_RATE_HZ
from drvs.core.object_types import object_type
from drvs.robot.cli import ENV_SERVER, check_seconds, parse_numbers
from drvs.robot.client import DEFAULT_TRACK_RATE_HZ, DrvsClient, RetryPolicy
from drvs.ros2.convert import DEFAULT_CLOUD_STEP_M, DEFAULT_HEIGHT_M, Style, region_from_points
from drvs.ros2.dds import QOS_PROFILES
from drvs.wire._cli import (
    add_security_arguments,
    env,
    join_negative_values,
    security_from,
    setup_logging,
    shutdown_event,
)
from drvs.wire.logs import FORMATS

PROG = "drvs-ros2"
EXIT_BAD_INPUT = 2
EXIT_UNAVAILABLE = 4
#: The DDS domain ROS 2 uses when ROS_DOMAIN_ID is not set; 232 is the most Cyclone accepts.
MAX_DOMAIN_ID = 232
TOPIC_PREFIX = re.compile(r"^(/[A-Za-z][A-Za-z0-9_]*)+$")


def parse_region(text: str) -> list[tuple[float, float]]:
    """--region: a box X0,Y0,X1,Y1 or a polygon X0,Y0,X1,Y1,X2,Y2,..., as corners."""
    values = parse_numbers(text, "--region")
    if len(values) == 4:
        x0, y0, x1, y1 = values
        if not (x0 < x1 and y0 < y1):
            raise InvalidArgument(f"--region: the box {text!r} needs X0 < X1 and Y0 < Y1")
        return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    if len(values) % 2 or len(values) < 6:
        raise InvalidArgument(
            f"--region: {len(values)} numbers: a box X0,Y0,X1,Y1 or a polygon's X,Y pairs (three points at least)"
        )
    return [(values[i], values[i + 1]) for i in range(0, len(values), 2)]


def parse_heights(items: list[str]) -> dict[str, float]:
    """--height TYPE=M, repeated: the box height of each object type (class_id), metres."""
    heights: dict[str, float] = {}
    for item in items:
        kind, sep, value = item.partition("=")
        try:
            metres = float(value)
        except ValueError:
            metres = math.nan
        if not sep or not kind or not math.isfinite(metres) or metres <= 0:
            raise InvalidArgument(f"--height: {item!r}: expected TYPE=METRES with a height > 0, e.g. person=1.8")
        heights[kind] = metres
    return heights


def domain_id(given: int | None) -> int:
    """--domain-id, else ROS_DOMAIN_ID, else 0; InvalidArgument outside [0, MAX_DOMAIN_ID]."""
    if given is None:
        text = os.environ.get("ROS_DOMAIN_ID") or "0"
        try:
            given = int(text)
        except ValueError:
            raise InvalidArgument(f"ROS_DOMAIN_ID: {text!r} is not a number") from None
    if not 0 <= given <= MAX_DOMAIN_ID:
        raise InvalidArgument(f"--domain-id (or ROS_DOMAIN_ID): {given} must be in [0, {MAX_DOMAIN_ID}]")
    return given


def check_args(args: argparse.Namespace) -> None:
    object_type(args.filter)  # an unknown or malformed filter is refused before anything connects
    check_seconds(args.rate, "--rate", 0, MAX_RATE_HZ, open_low=True)
    check_seconds(args.duration, "--duration", 0, math.inf, open_low=False)
    args.domain_id = domain_id(args.domain_id)
    if not TOPIC_PREFIX.match(args.topic_prefix):
        raise InvalidArgument(f"--topic-prefix: {args.topic_prefix!r} is not a ROS 2 namespace such as /drvs")
    if not args.frame_id or args.frame_id.startswith("/"):
        raise InvalidArgument(f"--frame-id: {args.frame_id!r}: a TF frame id, not empty, no leading '/'")
    for flag, value in (("--cloud-step", args.cloud_step), ("--default-height", args.default_height)):
        if not (math.isfinite(value) and value > 0):
            raise InvalidArgument(f"{flag}: {value:g} must be > 0")


async def run(args: argparse.Namespace) -> int:
    # Everything is checked before DDS or the network is touched.
    check_args(args)
    region = region_from_points(parse_region(args.region), "--region")
    style = Style(
        frame_id=args.frame_id,
        heights=parse_heights(args.height),
        default_height_m=args.default_height,
        cloud_step_m=args.cloud_step,
        filter_def=args.filter,
    )
    from drvs.ros2.bridge import Bridge, Following, Publisher, SimClock
    from drvs.ros2.dds import Node

    following = Following(args.filter, region, args.rate, args.duration, args.drop_after, args.deadline)
    try:
        node = Node(args.domain_id)  # DDS first: a bad CYCLONEDDS_URI is said before any network wait
    except DDSException as exc:
        raise InvalidArgument(
            f"Cyclone DDS would not start on domain {args.domain_id} ({exc}): check CYCLONEDDS_URI"
        ) from None
    stop = shutdown_event()
    async with DrvsClient.connect(
        args.server,
        robot_id=args.robot_id,
        security=security_from(vars(args)),
        retry=RetryPolicy.retries(args.retries),
        frame=args.frame or DEFAULT_FRAME,
    ) as client:
        publisher = Publisher(node, style, args.topic_prefix, args.qos, SimClock() if args.use_sim_time else None)
        bridge = Bridge(client, node, publisher, following, echo=args.json)
        running = asyncio.ensure_future(bridge.run())
        stopping = asyncio.ensure_future(stop.wait())
        await asyncio.wait({running, stopping}, return_when=asyncio.FIRST_COMPLETED)
        stopping.cancel()
        if not running.done():
            running.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await running
        print(f"{PROG}: stopped after {publisher.published} snapshot(s) in {bridge.tracks} track(s)", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="Publish a fused DRVS track on ROS 2 topics (Cyclone DDS).")
    p.add_argument(
        "--server",
        default=env(ENV_SERVER, "127.0.0.1:50051"),
        help=f"HOST:PORT, several sharing a registry (A:PORT,B:PORT), or a DNS name for several (env {ENV_SERVER})",
    )
    p.add_argument("--filter", required=True, help="filter_def, e.g. hsv_014110130035225200 (yellow) or people")
    p.add_argument(
        "--region", required=True, help="box X0,Y0,X1,Y1 or polygon X0,Y0,X1,Y1,X2,Y2,... in metres (/drvs/region)"
    )
    p.add_argument("--rate", type=float, default=DEFAULT_TRACK_RATE_HZ, metavar="HZ", help="snapshots per second")
    p.add_argument(
        "--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0: run until stopped)"
    )
    p.add_argument("--frame-id", default="map", help="header.frame_id of everything published (default map)")
    p.add_argument("--frame", default=None, help="the DRVS floor plan the region is in (default map)")
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="DDS domain, as ROS_DOMAIN_ID (default: env ROS_DOMAIN_ID, else 0)",
    )
    p.add_argument("--topic-prefix", default="/drvs", help="namespace of the topics (default /drvs)")
    p.add_argument(
        "--qos",
        choices=QOS_PROFILES,
        default="reliable",
        help="reliable (default) or sensor (best effort); keep last 10",
    )
    p.add_argument(
        "--height",
        action="append",
        default=[],
        metavar="TYPE=M",
        help="box height of an object type (its class_id: the label, else the filter), repeatable",
    )
    p.add_argument("--default-height", type=float, default=DEFAULT_HEIGHT_M, metavar="M", help="height of other types")
    p.add_argument(
        "--cloud-step", type=float, default=DEFAULT_CLOUD_STEP_M, metavar="M", help="obstacle point spacing, metres"
    )
    p.add_argument("--use-sim-time", action="store_true", help="stamp with /clock (rosgraph_msgs/Clock) time")
    p.add_argument("--drop-after", type=float, default=None, metavar="S", help="drop a track unseen this long")
    p.add_argument("--deadline", type=float, default=None, metavar="S", help="how late a camera's report still counts")
    p.add_argument("--json", action="store_true", help="print each published snapshot as drvs-robot track --json does")
    p.add_argument("--robot-id", default=PROG)
    p.add_argument("--retries", type=int, default=0, metavar="N", help="retries, with backoff, while no server answers")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--log-format", choices=FORMATS, default=None, help="text or json (env DRVS_LOG_FORMAT)")
    add_security_arguments(p, "file holding this robot's client token")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(join_negative_values(sys.argv[1:] if argv is None else argv, ("--region",)))
    setup_logging(args.log_level, args.log_format)
    try:
        return asyncio.run(run(args))
    except Unavailable as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_UNAVAILABLE
    except DrvsError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
