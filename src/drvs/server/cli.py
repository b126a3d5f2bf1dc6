"""drvs-server: the DRVS server process."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
from pathlib import Path

from drvs.core.errors import DrvsError, InvalidArgument
from drvs.live.liveview import parse_listen, require
from drvs.server import workers
from drvs.server.config import ENVIRONMENT, ServerConfig, add_arguments, from_arguments
from drvs.server.liveview import load_floor_plan
from drvs.server.server import DrvsServer
from drvs.wire._cli import (
    add_observability_arguments,
    add_security_arguments,
    env,
    env_number,
    security_from,
    setup_logging,
    shutdown_event,
)
from drvs.wire.metrics import DEFAULT_METRICS_HOST, parse_metrics_address, serve_metrics
from drvs.wire.security import load_tokens

log = logging.getLogger("drvs.server")

ENV_LISTEN = ENVIRONMENT["listen"]
ENV_LEASE_TTL = ENVIRONMENT["lease_ttl_s"]
ENV_TRUST_NETWORK = ENVIRONMENT["trust_network"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drvs-server", description="Run the DRVS server (registry and routing).")
    add_arguments(p)  # every ServerConfig setting (drvs.server.config declares each flag)
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
    v = p.add_argument_group("live view and recording (pip install 'drvs[live]'; docs/operations.md)")
    v.add_argument(
        "--foxglove",
        default=None,
        metavar="HOST:PORT",
        help="serve a Foxglove live view (WebSocket) here: cameras' fields of view, requests' regions, detections, "
        "tracks, and what robots publish to it; PORT alone listens on 127.0.0.1. Anyone who reaches it sees "
        "the building: keep it on loopback or a trusted network, or give it --foxglove-token (DRVS_FOXGLOVE)",
    )
    v.add_argument(
        "--foxglove-token",
        default=None,
        metavar="TOKEN",
        help="the live view takes only WebSockets that present this token (open ws://HOST:PORT/?token=TOKEN, "
        "or send 'Authorization: Bearer TOKEN'); others get 401. Prefer the variable: DRVS_FOXGLOVE_TOKEN",
    )
    v.add_argument(
        "--record-max-rate",
        default=None,
        type=float,
        metavar="MIB_PER_S",
        help="the most the live view and the recording take in a second, on average (MiB, before compression; "
        "bursts of twice that); beyond it messages are dropped and counted (default 8; DRVS_RECORD_MAX_RATE)",
    )
    v.add_argument(
        "--record",
        default=None,
        metavar="FILE.mcap",
        type=Path,
        help="record the live view's channels and every request, reply and report to this MCAP file "
        "(replaced if it exists; drvs-replay plays it back; DRVS_RECORD)",
    )
    v.add_argument(
        "--floor-plan",
        default=None,
        metavar="FILE",
        type=Path,
        help="walls to draw in the live view: a scenario YAML or a file with `walls:` polygons (DRVS_FLOOR_PLAN)",
    )
    add_security_arguments(p, "unused by the server (it checks tokens, it presents none)")
    add_observability_arguments(p)
    return p


async def serve(args: argparse.Namespace) -> None:
    stop = shutdown_event()
    server = DrvsServer.from_config(
        args.config,
        security=args.security,
        camera_tokens=args.camera_token_table,
        robot_tokens=args.robot_token_table,
    )
    if args.live is not None or args.record is not None:
        server.show(args.live, args.record, args.floor_plan, token=args.live_token, bytes_per_s=args.live_rate)
    await server.start()
    if args.metrics is not None:
        serve_metrics(args.metrics[1], args.metrics[0])
    try:
        await stop.wait()
        log.info("shutting down")
    finally:
        await server.stop(grace=2.0)


def config_from(args: argparse.Namespace) -> ServerConfig:
    """The flags (None: not given) and the DRVS_* environment as one validated ServerConfig."""
    return from_arguments(args, os.environ)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    index = workers.worker_index()
    try:
        args.config = config_from(args)
        if args.config.workers > 1 and index is None and (args.foxglove or args.record or env("DRVS_FOXGLOVE")):
            raise InvalidArgument(
                "--workers: the live view and the recording (--foxglove, --record) are one process's; "
                "run them on a single server"
            )
        metrics_host = args.metrics_host or env("DRVS_METRICS_HOST", DEFAULT_METRICS_HOST) or DEFAULT_METRICS_HOST
        if args.metrics_port is not None:
            args.metrics = parse_metrics_address(args.metrics_port, "--metrics-port", metrics_host)
        else:
            args.metrics = parse_metrics_address(
                env("DRVS_METRICS_PORT", "-1") or "-1", "DRVS_METRICS_PORT", metrics_host
            )
        if index is not None and args.metrics is not None and args.metrics[1]:
            args.metrics = (args.metrics[0], args.metrics[1] + index)  # worker i: the port P + i
        args.security = security_from(vars(args))
        live = args.foxglove or env("DRVS_FOXGLOVE")
        args.live = parse_listen(live, "--foxglove") if live else None
        args.record = args.record or (Path(r) if (r := env("DRVS_RECORD")) else None)
        args.floor_plan = args.floor_plan or (Path(f) if (f := env("DRVS_FLOOR_PLAN")) else None)
        args.live_token = args.foxglove_token or env("DRVS_FOXGLOVE_TOKEN")
        if args.live_token is not None and (len(args.live_token) < 16 or not args.live_token.isprintable()):
            raise InvalidArgument("--foxglove-token: at least 16 printable characters (e.g. `openssl rand -hex 16`)")
        if args.live_token is not None and args.live is None:
            raise InvalidArgument("--foxglove-token: only with a live view (--foxglove)")
        rate = args.record_max_rate if args.record_max_rate is not None else env_number("DRVS_RECORD_MAX_RATE", 8.0)
        if not 0 < rate < 1 << 20:
            raise InvalidArgument(f"--record-max-rate: {rate:g} is not a rate above 0 (MiB a second)")
        args.live_rate = rate * (1 << 20)
        if args.live is not None or args.record is not None:
            require("--foxglove" if args.live is not None else "--record")
            if args.floor_plan is not None:
                load_floor_plan(args.floor_plan)  # a bad file is named before anything starts
        elif args.floor_plan is not None:
            raise InvalidArgument("--floor-plan: only drawn in a live view or a recording (--foxglove, --record)")
        for role in ("camera", "robot"):
            path = getattr(args, f"{role}_tokens") or env(f"DRVS_{role.upper()}_TOKENS")
            setattr(args, f"{role}_token_table", load_tokens(Path(path), f"--{role}-tokens") if path else None)
    except DrvsError as exc:
        parser.error(str(exc))
    setup_logging(args.log_level, args.log_format)
    if args.config.workers > 1 and index is None:
        return workers.run(argv, args.config.listen, args.config.workers)
    try:
        asyncio.run(serve(args))
    except DrvsError as exc:
        log.error("%s", exc)
        return 2
    except OSError as exc:
        log.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
