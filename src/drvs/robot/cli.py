"""drvs-robot: ask DRVS from the command line (what a robot's code does through DrvsClient)."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
from typing import Any

from drvs.core.errors import DrvsError, InvalidArgument
from drvs.core.model import (
    DEFAULT_FRAME,
    MAX_DURATION_S,
    MAX_FUSION_DEADLINE_S,
    MAX_FUSION_DROP_AFTER_S,
    MAX_RATE_HZ,
    Detection,
    DetectionReport,
    Snapshot,
)
from drvs.robot.client import (
    DEFAULT_TIMEOUT_S,
    DEFAULT_TRACK_RATE_HZ,
    Connecting,
    DetectionResult,
    DrvsClient,
    RegionLike,
    RetryPolicy,
)
from drvs.robot.snapshots import polygon_json, snapshot_json, snapshot_table
from drvs.wire._cli import add_security_arguments, env, join_negative_values, security_from, setup_logging
from drvs.wire.logs import FORMATS

ENV_SERVER = "DRVS_SERVER"


def parse_numbers(text: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise InvalidArgument(f"{name}: {text!r} is not a comma-separated list of numbers") from None


def parse_roi(args: argparse.Namespace) -> RegionLike:
    if args.roi and args.polygon:
        raise InvalidArgument("give --roi or --polygon, not both")
    if args.roi:
        values = parse_numbers(args.roi, "--roi")
        if len(values) != 4:
            raise InvalidArgument(f"--roi: expected X0,Y0,X1,Y1, got {len(values)} numbers")
        return values
    if args.polygon:
        values = parse_numbers(args.polygon, "--polygon")
        if len(values) % 2 or len(values) < 6:
            raise InvalidArgument("--polygon: expected X,Y pairs of at least three points: X0,Y0,X1,Y1,X2,Y2,...")
        return [values[i : i + 2] for i in range(0, len(values), 2)]
    raise InvalidArgument("a region is required: --roi X0,Y0,X1,Y1 or --polygon X0,Y0,X1,Y1,X2,Y2,...")


def detection_json(d: Detection) -> dict[str, Any]:
    return {
        "camera_id": d.camera_id,
        "filter_def": d.filter_def,
        "centroid": [round(d.centroid.x, 4), round(d.centroid.y, 4)],
        "ground_contact": [round(d.ground_contact.x, 4), round(d.ground_contact.y, 4)],
        "bounds": [round(v, 4) for v in d.bounds],
        "outline": []
        if d.outline.is_empty
        else [[round(x, 4), round(y, 4)] for x, y in list(d.outline.exterior.coords)[:-1]],
        "area_m2": round(d.area_m2, 5),
        "area_px": d.area_px,
        "pixel_box": [d.pixel_box.x, d.pixel_box.y, d.pixel_box.width, d.pixel_box.height],
        "score": round(d.score, 3),
        "marker_id": d.marker_id,
        "heading_deg": None if d.heading_deg is None else round(d.heading_deg, 2),
        "label": d.label,
    }


def report_json(r: DetectionReport) -> dict[str, Any]:
    out: dict[str, Any] = {
        "request_id": r.request_id,
        "camera_id": r.camera_id,
        "sequence": r.sequence,
        "final": r.final,
        "capture_time": r.capture_time,
        "detections": [detection_json(d) for d in r.detections],
    }
    if r.error:
        out["error"] = r.error
    return out


def coverage_json(result: DetectionResult) -> dict[str, Any]:
    """What a per-camera request did not see, as drvs-robot detect --json prints it last when it
    did not see it all: `request_id`, `complete` (every camera answered), `missing_cameras`
    ([{camera_id, code, message}]), `uncovered` (polygons, [[x, y], ...] each, metres) and
    `uncovered_m2`."""
    return {
        "request_id": result.request_id,
        "complete": result.complete,
        "missing_cameras": [
            {"camera_id": e.camera_id, "code": e.code, "message": e.message}
            for _, e in sorted(result.camera_errors.items())
        ],
        "uncovered": [polygon_json(p) for p in result.uncovered],
        "uncovered_m2": round(sum(p.area for p in result.uncovered), 4),
    }


def print_report(r: DetectionReport) -> None:
    head = f"{r.camera_id} #{r.sequence}{' final' if r.final else ''}: "
    if r.error:
        print(head + f"error: {r.error}")
        return
    print(head + (f"{len(r.detections)} object(s)" if r.detections else "nothing seen"))
    for d in r.detections:
        x0, y0, x1, y1 = d.bounds
        print(
            f"    centroid ({d.centroid.x:7.3f}, {d.centroid.y:7.3f}) m  "
            f"bounds [{x0:.2f}, {y0:.2f}, {x1:.2f}, {y1:.2f}]  area {d.area_m2:.3f} m²  score {d.score:.2f}"
        )


def check_seconds(value: float | None, flag: str, low: float, high: float, *, open_low: bool) -> None:
    """A flag's number of seconds (or hertz) in its range, or InvalidArgument naming the flag."""
    if value is None:
        return
    inside = math.isfinite(value) and (value > low if open_low else value >= low) and value <= high
    if not inside and high == math.inf:
        raise InvalidArgument(f"{flag}: {value:g} must be >= {low:g}")
    if not inside:
        bracket = "(" if open_low else "["
        raise InvalidArgument(f"{flag}: {value:g} must be in {bracket}{low:g}, {high:g}]")


def check_fused_flags(args: argparse.Namespace, command: str) -> None:
    """The flags of a fused request (drvs-robot track, detect --fuse), checked before connecting."""
    if command == "track":
        check_seconds(args.rate, "--rate", 0, MAX_RATE_HZ, open_low=True)
        check_seconds(args.duration, "--duration", 0, MAX_DURATION_S, open_low=True)
        check_seconds(args.drop_after, "--drop-after", 0, MAX_FUSION_DROP_AFTER_S, open_low=False)
    else:
        if args.rate or args.duration:
            raise InvalidArgument("--fuse: a single shot; drvs-robot track gives snapshots at --rate for --duration")
        for flag, value in (("--listen", args.listen), ("--advertise", args.advertise)):
            if value:
                raise InvalidArgument(f"{flag}: a fused request needs no listener (--fuse)")
    check_seconds(args.deadline, "--deadline", 0, MAX_FUSION_DEADLINE_S, open_low=False)
    check_seconds(args.timeout, "--timeout", 0, math.inf, open_low=False)


def report_missing(snapshots: list[Snapshot]) -> bool:
    """Print each camera missing from any snapshot once (the latest reason), and how much of the
    region no camera saw; True if a camera was missing or some of the region went unseen."""
    missing: dict[str, tuple[int, str]] = {}
    for s in snapshots:
        for m in s.camera_errors.values():
            count, _ = missing.get(m.camera_id, (0, ""))
            missing[m.camera_id] = (count + 1, f"{m.code} {m.message}")
    for camera_id, (count, why) in sorted(missing.items()):
        times = "" if len(snapshots) == 1 else f" in {count} of {len(snapshots)} snapshots"
        print(f"drvs-robot: no answer from {camera_id}{times}: {why}", file=sys.stderr)
    unseen = max((sum(p.area for p in s.uncovered) for s in snapshots), default=0.0)
    if unseen:
        print(f"drvs-robot: {unseen:.1f} m² of the region unseen (no camera asked sees it)", file=sys.stderr)
    return bool(missing) or any(s.uncovered for s in snapshots)


def print_snapshot(snapshot: Snapshot, as_json: bool) -> None:
    if as_json:
        print(json.dumps(snapshot_json(snapshot)), flush=True)
    else:
        print("\n".join(snapshot_table(snapshot)), flush=True)


def connecting(args: argparse.Namespace, *, listener: bool = False) -> Connecting:
    """The client the flags describe (server, robot id, security, retries; with `listener`, the
    report listener's --listen and --advertise), connecting."""
    places = {"listen": args.listen, "advertise": args.advertise} if listener else {}
    return DrvsClient.connect(
        args.server,
        robot_id=args.robot_id,
        security=security_from(vars(args)),
        retry=RetryPolicy.retries(args.retries),
        frame=args.frame or DEFAULT_FRAME,
        **places,
    )


def continuous_flags(args: argparse.Namespace) -> dict[str, Any]:
    """What --rate, --duration, --timeout and --no-outlines ask of a subscription or a track."""
    return {
        "rate_hz": args.rate,
        "duration_s": args.duration,
        "timeout_s": args.timeout,
        "outlines": not args.no_outlines,
    }


async def detect_fused(args: argparse.Namespace) -> int:
    region = parse_roi(args)
    check_fused_flags(args, "detect")
    async with connecting(args) as client:
        snapshot = await client.snapshot(
            args.filter,
            region,
            deadline_s=args.deadline,
            timeout_s=args.timeout,
            outlines=not args.no_outlines,
        )
    print_snapshot(snapshot, args.json)
    return 3 if report_missing([snapshot]) else 0


async def track(args: argparse.Namespace) -> int:
    region = parse_roi(args)
    check_fused_flags(args, "track")
    seen: list[Snapshot] = []
    async with (
        connecting(args) as client,
        client.track(
            args.filter, region, drop_after_s=args.drop_after, deadline_s=args.deadline, **continuous_flags(args)
        ) as tracking,
    ):
        if not args.json:
            print(f"request {tracking.request_id}: dispatched to {', '.join(tracking.camera_ids) or 'no camera'}")
        async for snapshot in tracking:
            seen.append(snapshot)
            print_snapshot(snapshot, args.json)
        if tracking.dropped:
            print(f"drvs-robot: {tracking.dropped} snapshot(s) dropped unread", file=sys.stderr)
    return 3 if report_missing(seen) else 0


async def detect(args: argparse.Namespace) -> int:
    if args.fuse:
        return await detect_fused(args)
    if args.deadline is not None:
        raise InvalidArgument("--deadline: only with --fuse (or drvs-robot track)")
    region = parse_roi(args)
    async with (
        connecting(args, listener=True) as client,
        client.subscribe(args.filter, region, **continuous_flags(args)) as sub,
    ):
        if not args.json:
            print(f"request {sub.request_id}: dispatched to {', '.join(sub.camera_ids) or 'no camera'}")
        async for report in sub:
            if args.json:
                print(json.dumps(report_json(report)), flush=True)
            else:
                print_report(report)
        result = sub.result
        for camera_id, error in sorted(result.camera_errors.items()):
            print(f"drvs-robot: no answer from {camera_id}: {error.code} {error.message}", file=sys.stderr)
        if result.uncovered:
            print(
                f"drvs-robot: {sum(p.area for p in result.uncovered):.1f} m² of the region unseen "
                "(no camera asked sees it)",
                file=sys.stderr,
            )
        if args.json and not result.all_seen:  # what went unseen, after the reports
            print(json.dumps(coverage_json(result)), flush=True)
        if result.coverage_uncertain_s and not args.json:  # a notice, not a failure: JSON lines stay reports
            print(
                f"drvs-robot: the server restarted recently; for {result.coverage_uncertain_s:.0f} s more "
                "it may not know every camera",
                file=sys.stderr,
            )
        if not result.all_seen:  # a camera missing, or floor nobody looked at: not "nothing there"
            return 3
    return 0


async def cameras(args: argparse.Namespace) -> int:
    region = parse_roi(args) if (args.roi or args.polygon) else None
    async with DrvsClient.connect(args.server, robot_id=args.robot_id, security=security_from(vars(args))) as client:
        # Every frame's cameras unless --frame names one.
        found = await client.cameras(region, frame=args.frame or "")
    for c in found:
        if args.json:
            coords = [[round(x, 4), round(y, 4)] for x, y in list(c.field_of_view.exterior.coords)[:-1]]
            line: dict[str, Any] = {
                "camera_id": c.camera_id,
                "address": c.address,
                "field_of_view": coords,
                "detector_kinds": list(c.detector_kinds),
                "lease_remaining_s": round(c.lease_remaining_s, 2),
                "mobile": c.mobile,
                "frame": c.frame,
            }
            if c.mobile:
                line["pose"] = (
                    None if c.pose is None else [round(c.pose.x, 4), round(c.pose.y, 4), round(c.pose.yaw, 4)]
                )
                line["pose_age_s"] = None if c.pose is None else round(c.pose_age_s, 3)
                line["unroutable"] = c.unroutable
            print(json.dumps(line))
        else:
            if c.field_of_view.is_empty:
                seen = "no field of view"
            else:
                x0, y0, x1, y1 = c.field_of_view.bounds
                seen = f"field of view {c.field_of_view.area:6.1f} m² within [{x0:.1f}, {y0:.1f}, {x1:.1f}, {y1:.1f}]"
            moving = ""
            if c.mobile:
                where = (
                    "no pose yet"
                    if c.pose is None
                    else (
                        f"at ({c.pose.x:.2f}, {c.pose.y:.2f}, {math.degrees(c.pose.yaw):.0f}°) {c.pose_age_s:.1f} s ago"
                    )
                )
                moving = f"  mobile, {where}" + (f", not routed: {c.unroutable}" if c.unroutable else "")
            print(
                f"{c.camera_id:12s} {c.address:22s} {seen}  lease {c.lease_remaining_s:.1f} s  "
                f"serves {','.join(c.detector_kinds)}{moving}"
            )
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drvs-robot", description="Ask DRVS where objects are.")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument(
            "--server",
            default=env(ENV_SERVER, "127.0.0.1:50051"),
            help=f"HOST:PORT, several sharing a registry (A:PORT,B:PORT), or a DNS name for several (env {ENV_SERVER})",
        )
        sp.add_argument("--roi", help="box X0,Y0,X1,Y1 in metres")
        sp.add_argument("--polygon", help="polygon X0,Y0,X1,Y1,X2,Y2,... in metres")
        sp.add_argument("--robot-id", default="drvs-robot-cli")
        sp.add_argument(
            "--frame",
            default=None,
            help="the floor plan the region is in, e.g. building-a/floor-2 (default map; cameras: every frame)",
        )
        sp.add_argument("--json", action="store_true", help="one JSON object per line")
        sp.add_argument("--log-level", default="WARNING")
        sp.add_argument("--log-format", choices=FORMATS, default=None, help="text or json (env DRVS_LOG_FORMAT)")
        add_security_arguments(sp, "file holding this robot's client token")

    def retries(sp: argparse.ArgumentParser) -> None:
        sp.add_argument(
            "--retries",
            type=int,
            default=0,
            metavar="N",
            help="try again, with backoff, while the server is unavailable (N retries after the first try)",
        )

    d = sub.add_parser("detect", help="detect objects in a region")
    common(d)
    d.add_argument("--filter", required=True, help="filter_def, e.g. hsv_014110130035225200 (yellow)")
    d.add_argument("--rate", type=float, default=0.0, metavar="HZ", help="continuous mode: reports per second")
    d.add_argument("--duration", type=float, default=0.0, metavar="S", help="continuous mode: for how long")
    d.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help="wait this long beyond the duration",
    )
    d.add_argument("--no-outlines", action="store_true", help="bounds, centroid, ground contact only (fewer bytes)")
    d.add_argument("--listen", default=None, help="HOST:PORT for the callback listener (default: ephemeral)")
    d.add_argument("--advertise", default=None, help="HOST:PORT cameras should call back, if not --listen")
    retries(d)
    d.add_argument(
        "--fuse",
        action="store_true",
        help="the server merges what the cameras see: one snapshot of world objects (no listener)",
    )
    d.add_argument(
        "--deadline",
        type=float,
        default=None,
        metavar="S",
        help="--fuse: the server answers with what it has this long after dispatch (default 2)",
    )
    d.set_defaults(func=detect)

    t = sub.add_parser("track", help="fused, tracked world objects in a region, one snapshot a period (no listener)")
    common(t)
    t.add_argument("--filter", required=True, help="filter_def, e.g. hsv_014110130035225200 (yellow)")
    t.add_argument("--rate", type=float, default=DEFAULT_TRACK_RATE_HZ, metavar="HZ", help="snapshots per second")
    t.add_argument("--duration", type=float, required=True, metavar="S", help="for how long, seconds")
    t.add_argument(
        "--drop-after",
        type=float,
        default=None,
        metavar="S",
        help="drop a track no camera has seen for this long (default 1)",
    )
    t.add_argument(
        "--deadline",
        type=float,
        default=None,
        metavar="S",
        help="how late after its period a camera's report still counts (default: one period)",
    )
    t.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help="wait this long beyond the duration for the final snapshot",
    )
    t.add_argument("--no-outlines", action="store_true", help="bounds and centroid only (fewer bytes)")
    retries(t)
    t.set_defaults(func=track)

    c = sub.add_parser("cameras", help="list the registered cameras (optionally those seeing a region)")
    common(c)
    c.set_defaults(func=cameras)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(
        join_negative_values(sys.argv[1:] if argv is None else argv, ("--roi", "--polygon"))
    )
    setup_logging(args.log_level, args.log_format)
    try:
        return int(asyncio.run(args.func(args)))
    except DrvsError as exc:
        print(f"drvs-robot: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
