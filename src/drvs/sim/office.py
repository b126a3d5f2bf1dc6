"""drvs-office: the simulated office. A world, a DRVS server, camera nodes and a robot, each its
own process on loopback, run a mission; the run leaves result.json and map.png."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import cv2
import yaml

from drvs.core._files import folder_problem
from drvs.core.errors import DrvsError
from drvs.core.homography_file import save_homography
from drvs.live.liveview import parse_listen
from drvs.sim.cli import PROGRESS_PREFIX
from drvs.sim.scenario import DEFAULT_SCENARIO, CameraDef, Scenario, ScoutDef, load_scenario
from drvs.tools.certs import make_all
from drvs.tools.launch import LIVE_READY, ManagedProcess, cpu_seconds, start_camera, start_server, wait_serving

#: The run's recording, beside result.json (drvs-replay plays it back).
RECORDING = "run.mcap"
WORLD_READY = re.compile(r"sim world .* listening on (\S+)")
SCOUT_READY = re.compile(r"pose feed listening on (tcp://\S+)")


def sim_process(name: str, *args: str, echo: TextIO | None = None) -> ManagedProcess:
    return ManagedProcess.entry_point(name, "drvs-sim", *args, echo=echo)


def empty_floor(scenario: Scenario, camera: CameraDef, seed: int) -> Any:
    """What `drvs-camera snapshot` takes of the empty floor before the mission: this camera's view
    of the world without its obstacles (the unknown objects) and without the robot."""
    from drvs.sim.render import CameraRenderer

    empty = dataclasses.replace(scenario, objects=tuple(o for o in scenario.objects if o.kind != "obstacle"))
    return CameraRenderer(empty, camera, seed=seed).render(None, 0)


def camera_config(cams_dir: Path, scenario: Scenario, camera: CameraDef, detector: str, seed: int) -> list[str]:
    """Extra drvs-camera arguments for this detector: the detectors the mission uses (a camera runs
    every installed one by default, and foreground's motion model costs every frame whether or not
    anyone asks), and with `foreground` a config file naming a picture of the empty floor."""
    if detector != "foreground":
        return ["--detectors", "hsv,aruco"]
    picture = cams_dir / f"{camera.id}.empty.png"
    if not cv2.imwrite(str(picture), empty_floor(scenario, camera, seed)):
        raise OSError(f"cannot write {picture}")
    config = cams_dir / f"{camera.id}.camera.yaml"
    config.write_text(yaml.safe_dump({"background": str(picture.resolve())}))
    return ["--config", str(config), "--detectors", "hsv,aruco,foreground"]


async def start_scout(
    scout: ScoutDef, world: str, server: str, *args: str, echo: TextIO | None = None
) -> tuple[ManagedProcess, ManagedProcess]:
    """A scout's two processes: its mover (`drvs-sim scout`, its localisation: the world's poses of
    it as a tcp:// feed) and its camera (a mobile `drvs-camera` rendering the world from where the
    scout is, reading the mover's feed), returned once the camera has registered. `args`: more
    drvs-camera arguments (TLS, detectors)."""
    mover = await sim_process(f"{scout.id}-mover", "scout", "--world", world, "--id", scout.id, echo=echo).start()
    try:
        feed = (await mover.wait_for_line(SCOUT_READY)).group(1)
        m = scout.mount
        camera = await start_camera(
            scout.camera_id, f"sim://{world}", None, server,
            "--mount", f"{m.x:g},{m.y:g},{m.z:g},{m.yaw_deg:g},{m.pitch_deg:g}", "--hfov", f"{m.hfov_deg:g}",
            "--pose-source", feed, "--max-range", f"{scout.max_range_m:g}", *args, echo=echo,
        )  # fmt: skip
    except BaseException:
        await mover.stop()
        raise
    return mover, camera


class Progress:
    def __init__(self, quiet: bool, stream: TextIO) -> None:
        self.quiet = quiet
        self.stream = stream
        self.tty = stream.isatty()
        self._last_print = 0.0

    def show(self, p: dict[str, Any]) -> None:
        if self.quiet:
            return
        line = (
            f"t={p['t']:5.1f}s  robot at ({p['x']:6.2f}, {p['y']:6.2f})  "
            f"detections {p['detections']:2d}  re-plans {p['replans']:2d}  collisions {p['collisions']}"
        )
        if self.tty:
            print("\r" + line, end="", file=self.stream, flush=True)
        elif time.monotonic() - self._last_print >= 2.0:
            self._last_print = time.monotonic()
            print(line, file=self.stream, flush=True)

    def done(self) -> None:
        if self.tty and not self.quiet:
            print(file=self.stream)


async def run_office(args: argparse.Namespace, scenario: Scenario, scenario_path: Path, out: Path) -> int:
    echo = sys.stderr if args.verbose else None

    def say(text: str) -> None:
        if not args.quiet:
            print(text, flush=True)

    procs: list[ManagedProcess] = []
    cameras: dict[str, ManagedProcess] = {}
    server: ManagedProcess | None = None
    server_cpu_s: float | None = None
    progress = Progress(args.quiet, sys.stdout)
    try:
        world = await sim_process(
            "world", "world", "--scenario", str(scenario_path), "--seed", str(args.seed), echo=echo
        ).start()
        procs.append(world)
        world_address = (await world.wait_for_line(WORLD_READY)).group(1)
        await wait_serving(world_address, world)
        say(f"world      {scenario.name!r} on {world_address}")
        robot_args = ["robot", "--world", world_address, "--out", str(out), "--max-time", str(args.max_time)]
        robot_args += ["--detector", args.detector, "--delivery", args.delivery]
        if args.no_predict:
            robot_args.append("--no-predict")
        if args.no_drvs:
            robot_args.append("--no-drvs")
            say("DRVS       off: the paper's baseline, the robot learns obstacles by touching them")
        else:
            camera_ids = [c.id for c in scenario.cameras] + [s.camera_id for s in scenario.scouts]
            tls: dict[str, list[str]] = {"server": [], "robot": [], **{f"camera-{c}": [] for c in camera_ids}}
            if args.tls:
                certs = out / "certs"
                # One certificate per camera: each camera its own identity, so none can take over another's id.
                made = make_all(certs, ["server", "robot"], [], cameras=camera_ids)
                for role, (cert, key) in made.items():
                    tls[role] = ["--tls-cert", str(cert), "--tls-key", str(key), "--tls-ca", str(certs / "ca.pem"),
                                 "--tls-client-auth"]  # fmt: skip
                say(f"TLS        mutual TLS on every hop; certificates from drvs-certs in {certs}")
            view: list[str] = []
            if args.foxglove is not None or args.record:
                # The robot publishes into the server's live view, so a recording holds it too: with no
                # --foxglove the view listens on a port of loopback's own choosing, for the robot alone.
                host, port = args.foxglove or ("127.0.0.1", 0)
                view = ["--foxglove", f"{host}:{port}", "--floor-plan", str(scenario_path)]
                if args.record:
                    view += ["--record", str(out / RECORDING)]
            server, server_address = await start_server(*tls["server"], *view, echo=echo)
            procs.append(server)
            say(f"server     drvs-server on {server_address}")
            if view:
                live_url = next(m.group(1) for line in server.lines if (m := LIVE_READY.search(line)))
                robot_args += ["--live", live_url]
                if args.foxglove is not None:
                    say(
                        f"live view  {live_url}  (in Foxglove: Open connection, Foxglove WebSocket, this URL; "
                        "then a 3D panel, or docs/foxglove-layout.json)"
                    )
                if args.record:
                    say(f"recording  {out / RECORDING}")
            if args.detector == "foreground":
                say("detector   foreground: obstacles are anything not in each camera's picture of the empty floor")
            cams_dir = out / "cameras"
            cams_dir.mkdir(parents=True, exist_ok=True)
            for cam in scenario.cameras:
                hfile = cams_dir / f"{cam.id}.homography.yaml"
                save_homography(hfile, cam.homography, image_size=list(cam.resolution))
                proc = await start_camera(
                    cam.id, f"sim://{world_address}", hfile, server_address, "--max-range", str(cam.max_range_m),
                    *tls[f"camera-{cam.id}"], *camera_config(cams_dir, scenario, cam, args.detector, args.seed),
                    echo=echo,
                )  # fmt: skip
                procs.append(proc)
                cameras[cam.id] = proc
                say(f"camera     {cam.id} registered ({cam.field_of_view.floor.area:.1f} m² of floor)")
            for scout in scenario.scouts:
                # A moving camera has no picture of the empty floor to compare with: colours and markers.
                mover, camera = await start_scout(
                    scout, world_address, server_address, *tls[f"camera-{scout.camera_id}"],
                    "--detectors", "hsv,aruco", echo=echo,
                )  # fmt: skip
                procs += [mover, camera]
                cameras[scout.camera_id] = camera
                say(f"scout      {scout.id} drives {len(scout.path)} points at {scout.speed_mps:g} m/s; "
                    f"its camera {scout.camera_id} registered as mobile")  # fmt: skip
            robot_args += ["--server", server_address, *tls["robot"]]
        robot = await sim_process("robot", *robot_args, echo=echo).start()
        procs.append(robot)
        say(f"robot      mission {scenario.mission} from {list(scenario.robot.start)}")
        seen = 0
        while robot.returncode is None:
            try:
                await robot.wait_for_line(re.compile("^" + PROGRESS_PREFIX), timeout=args.max_time + 30, start=seen)
            except RuntimeError:
                break  # the robot exited
            for line in robot.lines[seen:]:
                if line.startswith(PROGRESS_PREFIX):
                    p = json.loads(line[len(PROGRESS_PREFIX) :])
                    progress.show(p)
                    if args.kill_camera and args.kill_camera[1] <= p["t"] and args.kill_camera[0] in cameras:
                        victim = cameras.pop(args.kill_camera[0])
                        victim.kill()  # a crash: no deregistration, no goodbye to the robot
                        say(f"\ncamera     {args.kill_camera[0]} killed at t={p['t']:.1f}s")
            seen = len(robot.lines)
        code = await robot.wait(timeout=30)
        progress.done()
        if code not in (0, 1):
            print(f"drvs-office: the robot failed (exit {code}):\n" + "\n".join(robot.lines[-15:]), file=sys.stderr)
    finally:
        if server is not None and server.returncode is None:
            with contextlib.suppress(OSError):  # what the server spent on the mission, before it stops
                server_cpu_s = cpu_seconds(server.pid)
        for proc in reversed(procs):
            await proc.stop()
    result_file = out / "result.json"
    if not result_file.exists():
        return 2
    result = json.loads(result_file.read_text())
    from drvs.sim.report import draw_map

    draw_map(scenario, result, out / "map.png", seed=args.seed)
    recording = out / RECORDING
    if args.record and recording.exists():
        result["recording"] = {"file": RECORDING, "bytes": recording.stat().st_size}
    if server_cpu_s is not None:
        result["server_cpu_s"] = round(server_cpu_s, 3)
    result_file.write_text(json.dumps(result, indent=1) + "\n")
    summarise(result, out, quiet=args.quiet)
    return code


def summarise(result: dict[str, Any], out: Path, quiet: bool) -> None:
    if quiet:
        print(out / "result.json")
        return
    print()
    print(f"mission          {result['mission']} {'with DRVS' if result['drvs'] else 'without DRVS (baseline)'}")
    if result.get("detector", "hsv") != "hsv":
        print(f"detector         {result['detector']}")
    print(f"reached goal     {'yes' if result['reached_goal'] else 'NO'}")
    if result["mission"] == "find_charging_station":
        print(f"charging station {result['charging_station']} (candidates {result['candidates']})")
    print(f"collisions       {result['collisions']}")
    print(f"re-plans         {result['replans']}")
    print(f"detections used  {len(result['detections'])}")
    loc = result["localisation"]
    if loc["fixes"]:
        heading = loc.get("mean_heading_error_deg")
        print(
            f"localisation     {loc['fixes']} DRVS fixes, mean error {loc['mean_error_m'] * 100:.1f} cm"
            + (f", heading {heading:.1f}°" if heading is not None else "")
            + (f" ({loc['filter_def']})" if loc.get("filter_def", "").startswith("aruco") else "")
        )
    for event in result.get("coverage_events", []):
        what = "stopped looking" if event["event"] == "lost" else "looks again"
        print(f"coverage         t={event['t']:.1f}s {event['camera_id']} {what} {event['why']}".rstrip())
    moving = [t for t in result.get("tracks", []) if str(t.get("used_as", "")).startswith("moving")]
    if result.get("tracks") is not None and result.get("delivery") == "fused":
        print(
            f"tracks           {len(result['tracks'])} followed, {len(moving)} moving; "
            f"{result.get('wait_steps', 0)} step(s) waited for one to pass"
        )
    if result.get("blind_steps"):
        print(f"blind steps      {result['blind_steps']} (slowed where no camera looks)")
    print(
        f"bytes to robot   {result['bytes_to_robot']:,} TCP payload, "
        f"{result.get('wire_bytes_to_robot', 0):,} on a 1500-MTU Ethernet link"
    )
    print(f"robot CPU        {result['robot_cpu_s']:.2f} s over {result['elapsed_s']:.1f} s")
    if result.get("failure"):
        print(f"failure          {result['failure']}")
    print(f"results          {out / 'result.json'}, {out / 'map.png'}")
    if result.get("recording"):
        rec = result["recording"]
        print(f"recording        {out / rec['file']} ({rec['bytes'] / 1e3:.0f} kB; drvs-replay plays it back)")


def parse_kill(text: str) -> tuple[str, float]:
    camera_id, sep, at = text.rpartition("@")
    try:
        seconds = float(at)
    except ValueError:
        seconds = math.nan
    if not sep or not camera_id or not (0 <= seconds < math.inf):
        raise DrvsError(f"--kill-camera: {text!r} is not ID@SECONDS (e.g. cam-east@1.5)")
    return camera_id, seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="drvs-office", description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", type=Path, default=None, help="scenario YAML (default: the paper's office)")
    parser.add_argument(
        "--mission", choices=["navigate", "find_charging_station"], help="override the scenario's mission"
    )
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a new drvs-out-* folder)")
    parser.add_argument("--seed", type=int, default=0, help="seed for sensor noise and lighting (default 0)")
    parser.add_argument("--no-drvs", action="store_true", help="the paper's baseline (Fig. 5): no DRVS")
    parser.add_argument("--tls", action="store_true", help="mutual TLS on every hop, with certificates from drvs-certs")
    parser.add_argument(
        "--detector",
        choices=["hsv", "foreground"],
        default="hsv",
        help="how obstacles are found: hsv, the scenario's obstacle colours (the paper's, default); "
        "foreground, anything that is not the empty floor (each camera gets a picture of it)",
    )
    parser.add_argument(
        "--delivery",
        choices=["fused", "per-camera"],
        default="fused",
        help="how the robot gets what cameras see: fused, tracked world objects from the server (default), or "
        "every camera's own reports (the paper's)",
    )
    parser.add_argument(
        "--no-predict",
        action="store_true",
        help="the robot ignores the velocity of moving obstacles (to compare with its prediction)",
    )
    parser.add_argument(
        "--kill-camera",
        metavar="ID@SECONDS",
        help="crash this camera (SIGKILL) once the robot has run SECONDS: where only it looked, the robot slows",
    )
    parser.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        help="a Foxglove live view of the office on ws://HOST:PORT while the mission runs (HOST: 127.0.0.1): "
        "walls, cameras, requests, detections, tracks, the robot and its paths",
    )
    parser.add_argument(
        "--no-record", dest="record", action="store_false", help=f"do not record the run to {RECORDING}"
    )
    parser.add_argument("--max-time", type=float, default=120.0, help="give the mission up after this many seconds")
    parser.add_argument("--quiet", "--headless", action="store_true", help="no progress; print only the result path")
    parser.add_argument("--verbose", action="store_true", help="show every process's log")
    args = parser.parse_args(argv)
    scenario_path = args.scenario or DEFAULT_SCENARIO
    out = args.out or Path(time.strftime("drvs-out-%Y%m%d-%H%M%S"))
    try:
        if (problem := folder_problem(out)) is not None:
            raise DrvsError(f"--out {out}: {problem}")
        if args.kill_camera:
            args.kill_camera = parse_kill(args.kill_camera)
        if args.foxglove is not None:
            args.foxglove = parse_listen(args.foxglove, "--foxglove")
        scenario = load_scenario(scenario_path)
        if args.kill_camera and args.kill_camera[0] not in {c.id for c in scenario.cameras} | {
            s.camera_id for s in scenario.scouts
        }:
            raise DrvsError(f"--kill-camera: the scenario has no camera {args.kill_camera[0]!r}")
        if args.mission and args.mission != scenario.mission:
            # The world, cameras and robot all read the scenario: give them the overridden one.
            out.mkdir(parents=True, exist_ok=True)
            scenario_path = out / "scenario.yaml"
            scenario_path.write_text(re.sub(r"(?m)^mission:.*$", f"mission: {args.mission}", scenario.source_text))
            scenario = load_scenario(scenario_path)
    except DrvsError as exc:
        print(f"drvs-office: {exc}", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    if not args.quiet:
        print(f"drvs-office: {scenario.name}, mission {scenario.mission}; results go to {out}/")
    return asyncio.run(run_office(args, scenario, scenario_path, out))
