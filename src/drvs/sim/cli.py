"""drvs-sim: the simulation's own roles, each a process: `world`, `scout` and `robot`."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
from pathlib import Path

from drvs.core.errors import DrvsError
from drvs.sim.poses import add_scout_arguments, scout_main
from drvs.sim.world import add_world_arguments, world_main
from drvs.wire._cli import add_security_arguments, security_from, setup_logging

log = logging.getLogger("drvs.sim")
PROGRESS_PREFIX = "PROGRESS "


def robot_main(args: argparse.Namespace) -> int:
    from drvs.sim.mission import run_robot

    setup_logging(args.log_level)

    def progress(p: dict[str, object]) -> None:
        print(PROGRESS_PREFIX + json.dumps(p), flush=True)

    try:
        result = asyncio.run(
            run_robot(
                args.world,
                None if args.no_drvs else args.server,
                Path(args.out),
                progress=progress,
                max_time_s=args.max_time,
                security=security_from(vars(args)),
                detector=args.detector,
                delivery=args.delivery,
                predict=not args.no_predict,
                live=args.live,
            )
        )
    except DrvsError as exc:
        log.error("%s", exc)
        return 2
    ok = bool(result["reached_goal"]) and (result["mission"] != "find_charging_station" or result["charging_station"])
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="drvs-sim", description="Simulation roles for DRVS.")
    sub = parser.add_subparsers(dest="role", required=True)
    w = sub.add_parser("world", help="serve the simulated world")
    add_world_arguments(w)
    w.set_defaults(func=world_main)
    sc = sub.add_parser("scout", help="serve a scout's poses from the world as a tcp:// pose feed (its localisation)")
    add_scout_arguments(sc)
    sc.set_defaults(func=scout_main)
    r = sub.add_parser("robot", help="run the simulated robot's mission")
    r.add_argument("--world", required=True, help="HOST:PORT of the simulated world")
    r.add_argument("--server", default="127.0.0.1:50051", help="HOST:PORT of the DRVS server")
    r.add_argument("--no-drvs", action="store_true", help="the paper's baseline: no DRVS, learn by touching")
    r.add_argument("--out", default=".", help="folder for result.json")
    r.add_argument(
        "--live",
        default=None,
        metavar="ws://HOST:PORT",
        help="publish the robot's pose, planned path and path driven into this Foxglove live view (a drvs-server's "
        "--foxglove)",
    )
    r.add_argument("--max-time", type=float, default=120.0, help="give up after this many seconds")
    r.add_argument(
        "--detector",
        choices=["hsv", "foreground"],
        default="hsv",
        help="find obstacles by the scenario's colours (hsv, the paper's) or as anything not empty floor",
    )
    r.add_argument(
        "--delivery",
        choices=["fused", "per-camera"],
        default="fused",
        help="fused (default): plan from the server's fused, tracked world objects; per-camera: every "
        "camera's reports, unioned (the paper's)",
    )
    r.add_argument(
        "--no-predict",
        action="store_true",
        help="take moving tracks to stand where they were last seen (to compare: the robot then ignores velocity)",
    )
    r.add_argument("--log-level", default=None)
    add_security_arguments(r, "file holding the robot's client token")
    r.set_defaults(func=robot_main)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
