"""drvs-server: the DRVS server process."""

from __future__ import annotations

import argparse
import asyncio
import logging
from pathlib import Path

from drvs._cli import (
    add_observability_arguments,
    add_security_arguments,
    env,
    env_number,
    security_from,
    setup_logging,
    shutdown_event,
)
from drvs.errors import DrvsError
from drvs.metrics import serve_metrics
from drvs.net import parse_address
from drvs.registry import DEFAULT_LEASE_TTL_S
from drvs.security import load_tokens
from drvs.server.policy import DEFAULT_MAX_ACTIVE, DEFAULT_RATE_HZ, CallbackPolicy, RequestLimits
from drvs.server.server import DEFAULT_FORWARD_TIMEOUT_S, DEFAULT_LISTEN, DEFAULT_MAX_QUEUED_FORWARDS, DrvsServer

log = logging.getLogger("drvs.server")

ENV_LISTEN = "DRVS_SERVER_LISTEN"
ENV_LEASE_TTL = "DRVS_LEASE_TTL"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drvs-server", description="Run the DRVS server (registry and routing).")
    p.add_argument(
        "--listen",
        default=env(ENV_LISTEN, DEFAULT_LISTEN),
        help=f"HOST:PORT to serve on; port 0 picks a free one (env {ENV_LISTEN}; default %(default)s)",
    )
    p.add_argument(
        "--lease-ttl",
        type=float,
        default=None,
        metavar="SECONDS",
        help=f"camera lease time-to-live (env {ENV_LEASE_TTL}; default {DEFAULT_LEASE_TTL_S:g})",
    )
    p.add_argument(
        "--forward-timeout",
        type=float,
        default=DEFAULT_FORWARD_TIMEOUT_S,
        metavar="SECONDS",
        help="how long a camera may take to accept a forwarded request (default %(default)s)",
    )
    p.add_argument(
        "--max-queued-forwards",
        type=int,
        default=DEFAULT_MAX_QUEUED_FORWARDS,
        metavar="N",
        help="requests waiting for one camera's acceptance at once; past this the robot is told at once "
        "that the camera is busy (default %(default)s)",
    )
    p.add_argument(
        "--allow-callback",
        action="append",
        default=[],
        metavar="CIDR",
        help="also let robots have reports sent to hosts in this network (repeatable); by default only to "
        "the requesting robot's own address",
    )
    p.add_argument(
        "--allow-any-callback", action="store_true", help="send reports wherever a request says (trusted networks only)"
    )
    p.add_argument(
        "--warm-up",
        type=float,
        default=None,
        metavar="SECONDS",
        help="after a start, replies say coverage is uncertain for this long: cameras registered with the "
        "server's previous run may not have registered again yet (default: the lease TTL; 0 for a new site)",
    )
    p.add_argument(
        "--camera-tokens",
        metavar="FILE",
        help="registration credentials: lines 'NAME TOKEN'; cameras must present one (env DRVS_CAMERA_TOKENS)",
    )
    p.add_argument(
        "--robot-tokens",
        metavar="FILE",
        help="client credentials: lines 'NAME TOKEN'; robots must present one (env DRVS_ROBOT_TOKENS)",
    )
    p.add_argument(
        "--rate-limit",
        type=float,
        default=DEFAULT_RATE_HZ,
        metavar="HZ",
        help="requests a second per robot (its credential, or its connection); burst twice that (default %(default)s)",
    )
    p.add_argument(
        "--max-continuous",
        type=int,
        default=DEFAULT_MAX_ACTIVE,
        metavar="N",
        help="continuous requests one robot may have running at once (default %(default)s)",
    )
    add_security_arguments(p, "unused by the server (it checks tokens, it presents none)")
    add_observability_arguments(p)
    return p


async def serve(args: argparse.Namespace) -> None:
    stop = shutdown_event()
    server = DrvsServer(
        args.listen,
        lease_ttl_s=args.lease_ttl,
        forward_timeout_s=args.forward_timeout,
        max_queued_forwards=args.max_queued_forwards,
        allow_callback=args.allow_callback,
        allow_any_callback=args.allow_any_callback,
        security=args.security,
        camera_tokens=args.camera_token_table,
        robot_tokens=args.robot_token_table,
        limits=args.limits,
        warm_up_s=args.warm_up,
    )
    await server.start()
    serve_metrics(args.metrics_port if args.metrics_port >= 0 else None)
    try:
        await stop.wait()
        log.info("shutting down")
    finally:
        await server.stop(grace=2.0)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        parse_address(args.listen, "--listen", allow_port_zero=True)
        if args.lease_ttl is None:
            args.lease_ttl = env_number(ENV_LEASE_TTL, DEFAULT_LEASE_TTL_S)
        if not 0 < args.lease_ttl <= 3600:
            raise DrvsError(f"--lease-ttl: {args.lease_ttl} must be in (0, 3600]")
        if args.warm_up is not None and not 0 <= args.warm_up <= 3600:
            raise DrvsError(f"--warm-up: {args.warm_up} must be in [0, 3600]")
        CallbackPolicy(args.allow_callback)  # refuses a malformed network now, not after start
        if not 0 < args.forward_timeout <= 60:
            raise DrvsError(f"--forward-timeout: {args.forward_timeout} must be in (0, 60]")
        if not 1 <= args.max_queued_forwards <= 100_000:
            raise DrvsError(f"--max-queued-forwards: {args.max_queued_forwards} must be in [1, 100000]")
        if not (0 < args.rate_limit <= 1e6 and 1 <= args.max_continuous <= 1e6):
            raise DrvsError("--rate-limit must be in (0, 1e6] and --max-continuous in [1, 1e6]")
        if args.metrics_port is None:
            args.metrics_port = int(env_number("DRVS_METRICS_PORT", -1, integer=True))
        if args.metrics_port > 65535:
            raise DrvsError(f"--metrics-port: {args.metrics_port} is not a port number (0 picks a free one)")
        args.limits = RequestLimits(args.rate_limit, max(1, round(2 * args.rate_limit)), args.max_continuous)
        args.security = security_from(vars(args))
        for role in ("camera", "robot"):
            path = getattr(args, f"{role}_tokens") or env(f"DRVS_{role.upper()}_TOKENS")
            setattr(args, f"{role}_token_table", load_tokens(Path(path), f"--{role}-tokens") if path else None)
    except DrvsError as exc:
        parser.error(str(exc))
    setup_logging(args.log_level, args.log_format)
    try:
        asyncio.run(serve(args))
    except OSError as exc:
        log.error("%s", exc)
        return 1
    return 0
