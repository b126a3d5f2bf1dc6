"""One run of the office as it ships (`drvs-office`, its default scenario and mission), watched live
the way Foxglove sees it. Two tests read it, each for its own checks: tests/live/test_liveview.py (the
live view and the recording) and tests/sim/test_office_moving.py (the trolley and the hidden obstacle).
The run is the same for both: drvs-office always serves its live view (--foxglove only fixes the
port) and records run.mcap, so the client watching changes nothing the mission does. Shared through
the session fixture `default_office` (tests/conftest.py): made once per test run, also across
pytest-xdist's workers (tests/helpers.py's once_per_run)."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from drvs.live.foxglove_client import Channel, FoxgloveClient
from drvs.live.liveview import SCENE_TOPICS
from drvs.tools.launch import ManagedProcess, free_ports


def decoder(channel: Channel) -> Any:
    """Decode a live view channel's messages with the schema it advertised, as Foxglove does."""
    schema = Schema(id=1, name=channel.schema_name, encoding=channel.schema_encoding, data=channel.schema)
    decode = DecoderFactory().decoder_for(channel.encoding, schema)
    assert decode is not None, channel
    return decode


@dataclass
class OfficeRun:
    """What the run left (exit code, its --out folder, result.json, its log) and what the live
    client saw while it ran (messages per topic, the robot's x and frame on /robot/pose, the
    entities on /robot/paths); `live_error` says what stopped the watching, if anything did (the
    live view's test fails on it, the mission's test reads the run regardless). JSON's types only,
    so that another worker can read it (once_per_run)."""

    code: int | None
    out: str
    result: dict[str, Any]
    log: str
    seen: dict[str, int] = field(default_factory=dict)
    pose_xs: list[float] = field(default_factory=list)
    pose_frames: list[str] = field(default_factory=list)
    robot_entities: list[str] = field(default_factory=list)
    live_error: str | None = None


async def watch(office: ManagedProcess, run: OfficeRun) -> None:
    """Until the robot has moved a metre with tracks in view: the office, moving, live."""
    url = (await office.wait_for_line(r"live view\s+(ws://\S+)", timeout=60)).group(1)
    async with await FoxgloveClient.connect(url) as client:
        topics = [*SCENE_TOPICS, "/robot/pose", "/robot/paths"]
        channels = await client.wait_for_topics(topics, timeout=60)
        await client.subscribe(channels.values())
        decoders = {t: decoder(c) for t, c in channels.items()}
        seen: Counter[str] = Counter()
        frames: set[str] = set()
        entities: set[str] = set()
        try:
            while not (len(run.pose_xs) > 1 and abs(run.pose_xs[-1] - run.pose_xs[0]) > 1.0
                       and seen["/drvs/tracks"] and seen["/drvs/cameras"]):  # fmt: skip
                message = await client.next_message(timeout=30)
                decoded = decoders[message.channel.topic](message.data)
                seen[message.channel.topic] += 1
                if message.channel.topic == "/robot/pose":
                    run.pose_xs.append(decoded.pose.position.x)
                    frames.add(decoded.frame_id)
                if message.channel.topic == "/robot/paths":
                    entities |= {e.id for e in decoded.entities}
        finally:
            run.seen, run.pose_frames, run.robot_entities = dict(seen), sorted(frames), sorted(entities)


async def run_default_office(out: Path) -> dict[str, Any]:
    """drvs-office --foxglove PORT (a fixed port, as Foxglove's users give it), watched live, to its
    end: the OfficeRun as a dict."""
    office = await ManagedProcess.entry_point(
        "office", "drvs-office", "--out", str(out), "--foxglove", str(free_ports(1)[0])
    ).start()
    run = OfficeRun(code=None, out=str(out), result={}, log="")
    try:
        try:
            await watch(office, run)
        except Exception as exc:  # the live view's test reports it; the mission goes on to its end
            run.live_error = f"watching the live view: {exc!r}"
        run.code = await office.wait(timeout=150)
    finally:
        await office.stop()
        run.log = office.output()
    result_file = out / "result.json"
    run.result = json.loads(result_file.read_text()) if result_file.exists() else {}
    return asdict(run)
