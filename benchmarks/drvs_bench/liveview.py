"""drvs-bench liveview: what the live view and the recording cost the office's mission.

The default office (drvs-office, default scenario, seed 0) in three modes, interleaved round by
round so a slow minute of this shared machine weighs on every mode alike:

- `off`: `--no-record`, no live view: the mission as it ran before either existed;
- `record`: the default, run.mcap written (the server's view listens on loopback for the robot's
  own pose and paths, with nobody watching);
- `live`: `--foxglove PORT` and run.mcap, with a viewer: a Foxglove-protocol client subscribed to
  every channel for the whole mission, as the Foxglove app is when someone watches.

Per run: the mission's wall time (the robot's `elapsed_s`), the server's CPU seconds (its process,
all threads, from /proc, just before it stops: foxglove-sdk's own threads count), the robot's CPU
seconds, run.mcap's size, and in `live` the bytes the viewer received (WebSocket payloads: what
the network carries to one Foxglove). Ratios are `live` and `record` over `off` within each round,
published as median and [min, max] over the rounds.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from operator import itemgetter
from pathlib import Path
from typing import Any

from drvs.live.foxglove_client import FoxgloveClient
from drvs.tools.launch import ManagedProcess, free_ports

from .common import machine, pyplot, write_result
from .stats import WorkMismatch, interleaved, measured, out_dir, per_round_ratio, publish

MODES = ("off", "record", "live")
#: Each round is three 25 s offices: 3 rounds take about 4 minutes.
FULL_ROUNDS = 3
QUICK_ROUNDS = 1


async def _watch(url: str, stop: asyncio.Event) -> dict[str, float]:
    """A viewer: subscribe to every channel as it is advertised; count what arrives until `stop`."""
    client = await FoxgloveClient.connect(url)
    subscribed: set[int] = set()
    received = {"messages": 0.0, "bytes": 0.0}
    try:
        while not stop.is_set():
            new = [c for c in client.channels.values() if c.id not in subscribed]
            if new:
                await client.subscribe(new)
                subscribed |= {c.id for c in new}
            try:
                message = await client.next_message(timeout=0.2)
            except TimeoutError:
                continue
            received["messages"] += 1
            received["bytes"] += 13 + len(message.data)  # the protocol's header + the message
    finally:
        await client.close()
    received["channels"] = float(len(subscribed))
    return received


async def _office(mode: str, out: Path) -> dict[str, Any]:
    args = ["--out", str(out)]
    if mode == "off":
        args.append("--no-record")
    if mode == "live":
        args += ["--foxglove", str(free_ports(1)[0])]
    proc = await ManagedProcess.entry_point(f"office-{mode}", "drvs-office", *args).start()
    stop = asyncio.Event()
    watcher: asyncio.Task[dict[str, float]] | None = None
    try:
        if mode == "live":
            # The viewer joins once the view listens (the office starts the server before the robot).
            url = (await proc.wait_for_line(r"live view\s+(ws://\S+)", timeout=120)).group(1)
            watcher = asyncio.get_running_loop().create_task(_watch(url, stop))
        code = await proc.wait(timeout=300)
    finally:
        stop.set()
        await proc.stop()
    seen = await watcher if watcher is not None else {}
    result = json.loads((out / "result.json").read_text())
    if code != 0 or not result.get("reached_goal"):
        raise WorkMismatch(f"office ({mode}): the mission failed (exit {code}): {result.get('failure')}")
    run = {
        "wall_s": result["elapsed_s"],
        "server_cpu_s": result["server_cpu_s"],
        "robot_cpu_s": result["robot_cpu_s"],
        "collisions": result["collisions"],
        "recording_bytes": result.get("recording", {}).get("bytes", 0),
    }
    if seen:
        run |= {"viewer_bytes": seen["bytes"], "viewer_messages": seen["messages"], "viewer_channels": seen["channels"]}
    return run


def figures(result: dict[str, Any]) -> dict[str, Any]:
    """The published figures of `result["runs"]` (one dict per round: mode -> that run's figures)."""
    runs = result["runs"]
    for mode in MODES:
        for key in ("wall_s", "server_cpu_s", "robot_cpu_s"):
            publish(result, f"{mode}_{key}", [r[mode][key] for r in runs])
    for mode in ("record", "live"):
        for key in ("wall_s", "server_cpu_s", "robot_cpu_s"):
            publish(result, f"{mode}_{key}_over_off", per_round_ratio(runs, itemgetter(key), mode, "off"))
        publish(result, f"{mode}_recording_bytes", [r[mode]["recording_bytes"] for r in runs])
        publish(result, f"{mode}_recording_bytes_per_s", [r[mode]["recording_bytes"] / r[mode]["wall_s"] for r in runs])
    publish(result, "live_viewer_bytes_per_s", [r["live"]["viewer_bytes"] / r["live"]["wall_s"] for r in runs])
    publish(result, "live_viewer_channels", [r["live"]["viewer_channels"] for r in runs])
    return result


async def run_liveview(out: Path, rounds: int) -> dict[str, Any]:
    runs: list[dict[str, dict[str, Any]]] = [{} for _ in range(rounds)]
    with tempfile.TemporaryDirectory(prefix="drvs-bench-liveview-") as tmp:
        for r, mode in interleaved(MODES, rounds):
            runs[r][mode] = await _office(mode, Path(tmp) / f"{mode}-{r}")
            print(f"round {r + 1}/{rounds} {mode}: {runs[r][mode]}", file=sys.stderr, flush=True)
    result = figures({"machine": machine(), "rounds": rounds, "runs": runs})
    write_result(result, out, "liveview", _plot)
    return result


def _plot(result: dict[str, Any], out: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, key, label in ((axes[0], "wall_s", "mission wall time (s)"), (axes[1], "server_cpu_s", "server CPU (s)")):
        medians = [result[f"{m}_{key}"] for m in MODES]
        lows = [medians[i] - result[f"{m}_{key}_spread"][0] for i, m in enumerate(MODES)]
        highs = [result[f"{m}_{key}_spread"][1] - medians[i] for i, m in enumerate(MODES)]
        ax.bar(MODES, medians, yerr=[lows, highs], capsize=4, color=["#999", "#69c", "#3a7"])
        ax.set_title(label)
    fig.suptitle(f"office with and without the live view: median and [min, max] of {result['rounds']} rounds")
    fig.tight_layout()
    fig.savefig(out / "liveview.png", dpi=100)
    plt.close(fig)


def liveview_main(args: argparse.Namespace) -> int:
    rounds = args.rounds or (QUICK_ROUNDS if args.quick else FULL_ROUNDS)
    if rounds < 1:
        print("drvs-bench liveview: --rounds must be > 0", file=sys.stderr)
        return 2
    out = out_dir(args.out)
    result = measured("liveview", lambda: asyncio.run(run_liveview(out, rounds)))
    if result is None:
        return 1
    summary = {
        k: result[k]
        for k in result
        if k.endswith(("_over_off", "_spread")) or k.startswith(("live_viewer", "record_recording"))
        if not k.endswith("_runs")
    }
    print(json.dumps(summary, indent=1))
    print(f"written: {out / 'liveview.json'}, {out / 'liveview.png'}")
    return 0


def add_liveview_parser(sub: Any) -> None:
    p = sub.add_parser("liveview", help="what the live view and the recording cost the office's mission")
    p.add_argument("--quick", action="store_true", help=f"a smoke run: {QUICK_ROUNDS} round(s) of the three modes")
    p.add_argument("--rounds", type=int, default=0, help=f"rounds of the three modes (full: {FULL_ROUNDS})")
    p.add_argument("--out", type=Path, default=None)
    p.set_defaults(func=liveview_main)
