"""The live view and the recording against forgeries and floods, with a real drvs-server (--foxglove,
--record), real gRPC callers and real Foxglove-protocol clients; the recording read back with mcap's
own reader. What is recorded passed the server's checks; clients publish only on channels of their
own, freed when they leave; what enters is bounded in size and rate; a token keeps strangers out."""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
from collections import defaultdict
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
from grpc import aio
from mcap.reader import make_reader
from mcap_protobuf.schema import build_file_descriptor_set
from websockets.exceptions import InvalidStatus

from drvs.live.foxglove_client import FoxgloveClient
from drvs.tools.launch import LIVE_READY, ManagedProcess, start_server
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from tests.helpers import detect_message, wait_until

TOKEN = "0123456789abcdef0123456789abcdef"


def recorded(path: Path) -> dict[str, list[bytes]]:
    """Every message of the recording by topic (mcap's own reader)."""
    by_topic: dict[str, list[bytes]] = defaultdict(list)
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            by_topic[channel.topic].append(message.data)
    return by_topic


@contextlib.asynccontextmanager
async def recording_server(tmp_path: Path, *args: str) -> AsyncIterator[tuple[ManagedProcess, str, str, Path]]:
    path = tmp_path / "site.mcap"
    server, address = await start_server("--foxglove", "127.0.0.1:0", "--record", str(path), *args)
    try:
        url = next(m.group(1) for line in server.lines if (m := LIVE_READY.search(line)))
        yield server, address, url, path
    finally:
        await server.stop()


async def test_a_forged_report_is_not_recorded(tmp_path: Path) -> None:
    """A report in camera left's name for a request nobody forwarded it (no key): the server
    rejects it, and neither the view nor the recording shows it under left's name."""
    async with recording_server(tmp_path) as (server, address, _, path):
        forged = detection_pb2.DetectionReport(
            request_id="forged-1",
            camera_id="left",
            final=True,
            detections=[detection_pb2.Detection(centroid=geometry_pb2.FloorPoint(x=1.0, y=5.0))],
        )
        async with aio.insecure_channel(address) as channel:
            call = detection_pb2_grpc.CallbackCoordinatesStub(channel).ReportDetections()
            await call.write(forged)
            await call.done_writing()
            cancelled = [i async for control in call for i in control.cancelled_request_ids]
        assert cancelled == ["forged-1"]
        await server.wait_for_line(r"report for request forged-1 in camera 'left''s name .* rejected", timeout=5)
    reports = recorded(path).get("/drvs/rpc/reports", [])
    assert not [r for r in reports if b"forged-1" in r], "a rejected report was recorded"


async def test_refused_requests_are_not_recorded_and_do_not_grow_the_file(tmp_path: Path) -> None:
    """Twenty 3 MB requests the server refuses (a region of 150 000 points, over its limit of
    1 000), and five small ones (an inverted box): before, each was recorded whole; now none is,
    and the file stays small."""
    rng = random.Random(5)
    region = geometry_pb2.Region(
        polygon=geometry_pb2.Polygon(
            points=[geometry_pb2.Point2(x=rng.uniform(0, 9), y=rng.uniform(0, 9)) for _ in range(150_000)]
        )
    )
    async with recording_server(tmp_path) as (_, address, _, path), aio.insecure_channel(address) as channel:
        stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
        for i in range(20):
            with pytest.raises(aio.AioRpcError) as refused:
                await stub.DetectObjects(detect_message(request_id=f"huge-{i}", region=region))
            assert refused.value.code() in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.RESOURCE_EXHAUSTED)
        inverted = geometry_pb2.Region(box=geometry_pb2.Box(x_lower=1, y_lower=0, x_upper=0, y_upper=1))
        for i in range(5):  # small ones too: refused, not recorded
            with pytest.raises(aio.AioRpcError) as refused:
                await stub.DetectObjects(detect_message(request_id=f"bad-{i}", region=inverted))
            assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        # One the server takes is recorded.
        await stub.DetectObjects(detect_message(request_id="fine"))
    requests = recorded(path)["/drvs/rpc/requests"]
    assert [detection_pb2.DetectionRequest.FromString(r).request_id for r in requests] == ["fine"]
    assert path.stat().st_size < 1 << 20, path.stat().st_size


async def test_a_client_publishes_only_on_its_own_channels_within_the_budget_and_they_go_when_it_does(
    tmp_path: Path,
) -> None:
    """A client may not publish on the server's /drvs/ topics (a forged reply on /drvs/rpc/replies is
    refused); what it may publish is a channel of its own, tagged with it, held to the hub's bytes a
    second (--record-max-rate 1: 1 MiB/s, bursts of 2 MiB), and unadvertised when it disconnects."""
    reply_schema = build_file_descriptor_set(detection_pb2.DetectionReply).SerializeToString()
    chunk = 512 * 1024
    flood = 40  # 20 MiB, offered at once
    async with recording_server(tmp_path, "--record-max-rate", "1") as (server, _, url, path):
        loop = asyncio.get_running_loop()
        started = loop.time()
        async with await FoxgloveClient.connect(url) as watcher:
            publisher = await FoxgloveClient.connect(url)
            replies = await publisher.advertise(
                "/drvs/rpc/replies", "protobuf", "drvs.v1.DetectionReply", reply_schema, "protobuf"
            )
            await server.wait_for_line(r"client \d+ may not publish '/drvs/rpc/replies'", timeout=5)
            await publisher.publish(replies, detection_pb2.DetectionReply(request_id="forged").SerializeToString())
            mine = await publisher.advertise("/robot/flood", "json", "Flood", b"{}", "jsonschema")
            seen = await watcher.wait_for_topics(["/robot/flood"])
            await watcher.subscribe(seen.values())
            # One over the size limit (1 MiB), first, while the budget is full: dropped all the same.
            await publisher.publish(mine, json.dumps(random.Random(-1).randbytes(3 * chunk // 2).hex()).encode())
            for i in range(flood):
                text = random.Random(i).randbytes(chunk // 2).hex()
                await publisher.publish(mine, json.dumps(text).encode())
            await watcher.next_message(timeout=10)  # some of it came through
            await publisher.close()
            # Its channel is freed: unadvertised to the watcher.
            await wait_until(
                lambda: all(c.topic != "/robot/flood" for c in watcher.channels.values()),
                "the client's channel unadvertised once it left",
                timeout=10,
            )
        elapsed = loop.time() - started
    assert any("messages dropped (too large, too fast, or behind)" in line for line in server.lines)
    by_topic = recorded(path)
    assert not [m for m in by_topic.get("/drvs/rpc/replies", []) if b"forged" in m]
    got = sum(len(m) for m in by_topic["/robot/flood"])
    assert max(len(m) for m in by_topic["/robot/flood"]) <= 1 << 20
    assert 0 < got <= (2 + 1 * elapsed) * (1 << 20) + chunk, (got, elapsed)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    flood_channels = [c for c in summary.channels.values() if c.topic == "/robot/flood"]
    assert [c.metadata.get("published_by", "")[:7] for c in flood_channels] == ["client "]


async def test_a_view_with_a_token_refuses_whoever_does_not_present_it(tmp_path: Path) -> None:
    async with recording_server(tmp_path, "--foxglove-token", TOKEN) as (_, _, url, _):
        for wrong in (None, "wrong-token-wrong-token"):
            with pytest.raises(InvalidStatus) as refused:
                await FoxgloveClient.connect(url, timeout=5, token=wrong)
            assert refused.value.response.status_code == 401
        with pytest.raises(InvalidStatus):
            await FoxgloveClient.connect(f"{url}/?token=nope", timeout=5)
        for target, token in ((url, TOKEN), (f"{url}/?token={TOKEN}", None)):  # a header, or the URL
            async with await FoxgloveClient.connect(target, token=token) as client:
                channels = await client.wait_for_topics(["/drvs/rpc/requests"])
                assert channels and client.server_info["name"] == "drvs-server"


async def test_a_view_beyond_loopback_is_warned_about_loudly(tmp_path: Path) -> None:
    server, _ = await start_server("--foxglove", "0.0.0.0:0")
    try:
        await server.wait_for_line(r"THE LIVE VIEW ON ws://0\.0\.0\.0:\d+ IS OPEN TO ANYONE", timeout=5)
    finally:
        await server.stop()
