"""Robot container entrypoint: the simulated office's robot, as drvs-office runs it, across containers.

    run-mission.py --world world:50070 --server server:50051 --out /out [--max-time S] [--no-drvs]
                   [--live ws://server:8765]

Waits for the world and for every camera of its scenario to be registered with the server, runs
`drvs-sim robot` (progress every 2 s), then draws map.png beside its result.json and prints the
summary. Exits with drvs-sim robot's code: 0 the mission succeeded, 1 it failed, 2 it could not run
(or left no result); 128+N when stopped by signal N (SIGTERM is passed on to the robot).

Started as root, it only makes /out writable: it runs as the owner of a mounted /out (so a person's
own folder gets files they own), or as the image's drvs user when root owns /out (the folder
Docker creates for a missing bind-mount source; it is made writable for all, so its owner on the
host can delete what the robot wrote).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

PROGRESS_PREFIX = "PROGRESS "


def say(text: str) -> None:
    print(f"robot: {text}", flush=True)


def drop_privileges(out: Path) -> None:
    if os.getuid() != 0:
        return
    import pwd

    drvs = pwd.getpwnam("drvs")
    out.mkdir(parents=True, exist_ok=True)
    st = out.stat()
    if st.st_uid == 0:
        out.chmod(0o777)
        uid, gid = drvs.pw_uid, drvs.pw_gid
    else:
        uid, gid = st.st_uid, st.st_gid
    os.setgroups([])
    os.setgid(gid)
    os.setuid(uid)
    os.environ["HOME"] = drvs.pw_dir if uid == drvs.pw_uid else "/tmp"
    os.environ.setdefault("MPLCONFIGDIR", "/tmp/matplotlib")


def fetch_scene(world: str) -> tuple[Any, int]:
    import grpc

    from drvs.core.errors import Unavailable
    from drvs.sim import world as sim_world

    with grpc.insecure_channel(world) as channel:
        try:
            return sim_world.fetch_scene(channel, world, 60)
        except Unavailable as exc:
            raise SystemExit(f"robot: {exc}") from None


def wait_for_cameras(server: str, wanted: set[str], timeout_s: float) -> None:
    """drvs-office starts the robot once every camera has registered; so does this."""
    import grpc

    from drvs.v1 import registry_pb2, registry_pb2_grpc

    deadline = time.monotonic() + timeout_s
    seen: set[str] = set()
    with grpc.insecure_channel(server) as channel:
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        while True:
            try:
                reply = stub.ListCameras(registry_pb2.ListCamerasRequest(), timeout=5, wait_for_ready=True)
                seen = {c.camera_id for c in reply.cameras}
            except grpc.RpcError:
                pass
            if wanted <= seen:
                return
            if time.monotonic() > deadline:
                missing = ", ".join(sorted(wanted - seen))
                raise SystemExit(f"robot: cameras not registered with {server} after {timeout_s:g} s: {missing}")
            time.sleep(0.5)


def main() -> int:
    p = argparse.ArgumentParser(prog="run-mission", description=__doc__.splitlines()[0])
    p.add_argument("--world", default="world:50070", help="HOST:PORT of the simulated world")
    p.add_argument("--server", default="server:50051", help="HOST:PORT of the DRVS server")
    p.add_argument("--out", type=Path, default=Path("/out"), help="folder for result.json and map.png")
    p.add_argument("--max-time", type=float, default=120.0, help="give the mission up after this many seconds")
    p.add_argument("--no-drvs", action="store_true", help="the paper's baseline: no DRVS, learn by touching")
    p.add_argument("--wait-cameras", type=float, default=90.0, help="seconds to wait for the cameras to register")
    p.add_argument("--live", default=None, help="ws://HOST:PORT of the server's live view, to publish the robot into")
    args = p.parse_args()

    stop_signal: list[int] = []
    child: subprocess.Popen[str] | None = None

    def on_signal(signum: int, _frame: object) -> None:
        stop_signal.append(signum)
        if child is None:
            raise SystemExit(128 + signum)
        child.send_signal(signum)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    drop_privileges(args.out)
    from drvs.sim.office import Progress, summarise
    from drvs.sim.report import draw_map

    scenario, seed = fetch_scene(args.world)
    say(f"world {args.world}: scenario {scenario.name!r}, mission {scenario.mission}, seed {seed}")
    if not args.no_drvs:
        wanted = {cam.id for cam in scenario.cameras} | {scout.camera_id for scout in scenario.scouts}
        wait_for_cameras(args.server, wanted, args.wait_cameras)
        say(f"server {args.server}: cameras {', '.join(sorted(wanted))} registered")
    result_file = args.out / "result.json"
    result_file.unlink(missing_ok=True)
    argv = ["drvs-sim", "robot", "--world", args.world, "--out", str(args.out), "--max-time", str(args.max_time)]
    argv += ["--no-drvs"] if args.no_drvs else ["--server", args.server]
    if args.live and not args.no_drvs:
        argv += ["--live", args.live]
    say(f"mission {scenario.mission} from {list(scenario.robot.start)}; results go to {args.out}/")
    progress = Progress(False, sys.stdout)
    child = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    assert child.stdout is not None
    for line in child.stdout:
        if line.startswith(PROGRESS_PREFIX):
            progress.show(json.loads(line[len(PROGRESS_PREFIX) :]))
        else:
            print(line, end="", flush=True)
    code = child.wait()
    if stop_signal:
        say(f"stopped by signal {stop_signal[0]}")
        return 128 + stop_signal[0]
    if code not in (0, 1):
        say(f"drvs-sim robot failed (exit {code})")
    if not result_file.exists():
        say(f"no {result_file}")
        return code if code not in (0, 1) else 2
    result = json.loads(result_file.read_text())
    draw_map(scenario, result, args.out / "map.png", seed=seed)
    summarise(result, args.out, quiet=False)
    return code


if __name__ == "__main__":
    sys.exit(main())
