"""drvs-server: the DRVS server process."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
from pathlib import Path

from drvs import _grpc
from drvs._cli import (
    add_observability_arguments,
    add_security_arguments,
    env,
    env_number,
    security_from,
    setup_logging,
    shutdown_event,
)
from drvs.errors import DrvsError, InvalidArgument
from drvs.liveview import parse_listen, require
from drvs.metrics import DEFAULT_METRICS_HOST, parse_metrics_address, serve_metrics
from drvs.registry import (
    DEFAULT_GRACE_S,
    DEFAULT_LEASE_TTL_S,
    DEFAULT_MAX_CAMERAS_PER_IDENTITY,
    DEFAULT_MAX_FOV_AREA_M2,
    DEFAULT_MAX_FOV_RANGE_M,
    DEFAULT_MIN_POSE_INTERVAL_S,
    DEFAULT_POSE_LEASE_S,
    MAX_POSE_LEASE_S,
)
from drvs.security import load_tokens
from drvs.server import workers
from drvs.server.config import (
    DEFAULT_FORWARD_TIMEOUT_S,
    DEFAULT_LISTEN,
    DEFAULT_MAX_QUEUED_FORWARDS,
    ENVIRONMENT,
    ServerConfig,
)
from drvs.server.liveview import load_floor_plan
from drvs.server.policy import DEFAULT_FORWARD_BYTES_PER_S, DEFAULT_MAX_ACTIVE, DEFAULT_RATE_HZ
from drvs.server.server import DrvsServer

log = logging.getLogger("drvs.server")

ENV_LISTEN = ENVIRONMENT["listen"]
ENV_LEASE_TTL = ENVIRONMENT["lease_ttl_s"]
ENV_TRUST_NETWORK = ENVIRONMENT["trust_network"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drvs-server", description="Run the DRVS server (registry and routing).")
    p.add_argument(
        "--listen",
        default=None,
        help=f"HOST:PORT to serve on; port 0 picks a free one (env {ENV_LISTEN}; default {DEFAULT_LISTEN})",
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
    p.add_argument(
        "--max-forward-bytes",
        type=float,
        default=DEFAULT_FORWARD_BYTES_PER_S,
        metavar="BYTES",
        help="bytes a second the server may forward to cameras for one robot (a request's size times the "
        "cameras it goes to); burst twice that (default %(default)d)",
    )
    g = p.add_argument_group("connections (0: no limit)")
    g.add_argument(
        "--max-streams-per-connection",
        type=int,
        default=_grpc.DEFAULT_MAX_STREAMS_PER_CONNECTION,
        metavar="N",
        help="calls one connection may have open at once; more wait on the client (default %(default)s)",
    )
    g.add_argument(
        "--max-connection-idle",
        type=float,
        default=_grpc.DEFAULT_MAX_CONNECTION_IDLE_S,
        metavar="SECONDS",
        help="close a connection that has had no call open this long (default %(default)g)",
    )
    g.add_argument(
        "--max-connection-age",
        type=float,
        default=_grpc.DEFAULT_MAX_CONNECTION_AGE_S,
        metavar="SECONDS",
        help="ask a client to reconnect after this long; clients reconnect by themselves (default %(default)g)",
    )
    g.add_argument(
        "--max-connection-age-grace",
        type=float,
        default=_grpc.DEFAULT_MAX_CONNECTION_AGE_GRACE_S,
        metavar="SECONDS",
        help="then end the old connection's calls this much later (default %(default)g)",
    )
    p.add_argument(
        "--trust-network",
        action="store_const",
        const=True,
        help="let cameras register without a credential although --listen is beyond this host: everyone who "
        f"can reach the port is trusted (env {ENV_TRUST_NETWORK}=1; default: only on loopback)",
    )
    p.add_argument(
        "--registration-grace",
        type=float,
        default=DEFAULT_GRACE_S,
        metavar="SECONDS",
        help="a camera id stays with whoever registered it this long after its lease ran out (default %(default)s)",
    )
    p.add_argument(
        "--max-cameras-per-identity",
        type=int,
        default=DEFAULT_MAX_CAMERAS_PER_IDENTITY,
        metavar="N",
        help="camera ids one credential (without one: one IP address) may hold (default %(default)s)",
    )
    p.add_argument(
        "--max-fov-range",
        type=float,
        default=DEFAULT_MAX_FOV_RANGE_M,
        metavar="M",
        help="largest max_range_m a camera may register with, metres (default %(default)s)",
    )
    p.add_argument(
        "--max-fov-area",
        type=float,
        default=DEFAULT_MAX_FOV_AREA_M2,
        metavar="M2",
        help="largest field of view one camera may register, square metres (default %(default)s)",
    )
    m = p.add_argument_group("mobile cameras (cameras on robots, whose field of view moves)")
    m.add_argument(
        "--pose-lease",
        type=float,
        default=DEFAULT_POSE_LEASE_S,
        metavar="SECONDS",
        help="route a mobile camera this long after its last pose update, unless it asks for another "
        "lease (default %(default)g)",
    )
    m.add_argument(
        "--max-pose-lease",
        type=float,
        default=MAX_POSE_LEASE_S,
        metavar="SECONDS",
        help="longest pose lease a mobile camera may ask for (default %(default)g)",
    )
    m.add_argument(
        "--min-pose-interval",
        type=float,
        default=DEFAULT_MIN_POSE_INTERVAL_S,
        metavar="SECONDS",
        help="refuse a mobile camera's pose update sooner than this after its previous one (default %(default)g)",
    )
    p.add_argument(
        "--registry",
        default=None,
        metavar="memory|etcd://HOST:PORT[,HOST:PORT...]",
        help="where the camera registry lives: in this server's memory (default), or in etcd, shared by "
        "every server given the same etcd (DRVS_REGISTRY)",
    )
    p.add_argument(
        "--registration-rate",
        type=float,
        default=None,
        metavar="N",
        help="on a registry in etcd: registrations one identity may make a minute, in bursts of N; more are "
        "refused RESOURCE_EXHAUSTED with a retry hint (default 60)",
    )
    p.add_argument(
        "--pose-write-rate",
        type=float,
        default=None,
        metavar="HZ",
        help="on a registry in etcd: pose updates one identity's mobile cameras may send a second, in bursts "
        "of HZ (default 50)",
    )
    p.add_argument(
        "--admission-target",
        type=float,
        default=None,
        metavar="SECONDS",
        help="refuse requests at once (RESOURCE_EXHAUSTED, with a retry hint) while the server's or a camera's "
        "queue stands longer than this (default 0.01; 0: admission off, for measuring raw capacity)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="serve --listen with N processes, so one host's cores all serve (the kernel spreads connections "
        "over them; they share the registry, so --registry etcd://... is needed; default 1)",
    )
    p.add_argument(
        "--advertise",
        default=None,
        metavar="HOST:PORT",
        help="where cameras send this server fused requests' reports, if not the --listen address (needed "
        "when cameras know several servers and this one listens on 0.0.0.0; DRVS_SERVER_ADVERTISE)",
    )
    e = p.add_argument_group("TLS to etcd (with --registry etcd://...)")
    e.add_argument("--etcd-ca", default=None, metavar="FILE", help="CA certificate etcd's members are checked against")
    e.add_argument(
        "--etcd-cert", default=None, metavar="FILE", help="this server's certificate, when etcd asks for one"
    )
    e.add_argument("--etcd-key", default=None, metavar="FILE", help="its private key")
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
    return ServerConfig.load(
        {
            "listen": args.listen,
            "lease_ttl_s": args.lease_ttl,
            "forward_timeout_s": args.forward_timeout,
            "max_queued_forwards": args.max_queued_forwards,
            "allow_callback": args.allow_callback,
            "allow_any_callback": args.allow_any_callback,
            "warm_up_s": args.warm_up,
            "rate_limit_hz": args.rate_limit,
            "max_continuous": args.max_continuous,
            "max_forward_bytes_per_s": args.max_forward_bytes,
            "max_streams_per_connection": args.max_streams_per_connection,
            "max_connection_idle_s": args.max_connection_idle,
            "max_connection_age_s": args.max_connection_age,
            "max_connection_age_grace_s": args.max_connection_age_grace,
            "trust_network": args.trust_network,
            "registration_grace_s": args.registration_grace,
            "max_cameras_per_identity": args.max_cameras_per_identity,
            "max_fov_range_m": args.max_fov_range,
            "max_fov_area_m2": args.max_fov_area,
            "pose_lease_s": args.pose_lease,
            "max_pose_lease_s": args.max_pose_lease,
            "min_pose_interval_s": args.min_pose_interval,
            "registry": args.registry,
            "registration_rate": args.registration_rate,
            "pose_write_rate": args.pose_write_rate,
            "advertise": args.advertise,
            "etcd_ca": args.etcd_ca,
            "etcd_cert": args.etcd_cert,
            "etcd_key": args.etcd_key,
            "workers": args.workers,
            "admission_target_s": args.admission_target,
        },
        os.environ,
    )


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
