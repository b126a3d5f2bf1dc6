"""A client of the Foxglove WebSocket protocol (what the Foxglove app speaks to a live view), on the
`websockets` library: subscribe to a live view's channels and read their messages, or advertise
channels and publish into it (the protocol's clientPublish).

The protocol: https://github.com/foxglove/ws-protocol (JSON text frames for control; binary frames
for data: opcode 1, then a little-endian u32 subscription id, a u64 log time in nanoseconds and the
message; a client's data is opcode 1, a u32 channel id and the message).

The office robot publishes its pose and paths with it (drvs.sim.robot), and the tests watch a live
view with it as Foxglove would."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import struct
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass, field
from typing import Any

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
MESSAGE_DATA = 1
TIME = 2
CLIENT_MESSAGE_DATA = 1


@dataclass(frozen=True)
class Channel:
    """A channel the server advertised."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: bytes
    schema_encoding: str


@dataclass(frozen=True)
class Message:
    channel: Channel
    log_time_ns: int
    data: bytes


@dataclass
class FoxgloveClient:
    """One connection to a live view. `await FoxgloveClient.connect(url)`; `close()` when done."""

    ws: Any
    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    _subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    _next_id: int = 1
    _messages: asyncio.Queue[Message] = field(default_factory=lambda: asyncio.Queue(maxsize=10_000))
    _advertised: asyncio.Event = field(default_factory=asyncio.Event)
    _reader: asyncio.Task[None] | None = None
    dropped: int = 0

    @classmethod
    async def connect(
        cls, url: str, *, timeout: float = 10.0, ssl: Any = None, token: str | None = None
    ) -> FoxgloveClient:
        """`token`: the view's (drvs-server --foxglove-token), sent as `Authorization: Bearer`."""
        import websockets

        headers = {"Authorization": f"Bearer {token}"} if token else None
        ws = await asyncio.wait_for(
            websockets.connect(
                url,
                subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
                max_size=None,
                ssl=ssl,
                additional_headers=headers,
            ),
            timeout,
        )
        client = cls(ws)
        first = json.loads(await asyncio.wait_for(ws.recv(), timeout))
        if first.get("op") != "serverInfo":
            await ws.close()
            raise ConnectionError(f"{url}: not a Foxglove live view (its first message is {first.get('op')!r})")
        client.server_info = first
        client._reader = asyncio.get_running_loop().create_task(client._read())
        return client

    async def close(self) -> None:
        await self.ws.close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader

    async def __aenter__(self) -> FoxgloveClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _read(self) -> None:
        async for frame in self.ws:
            if isinstance(frame, str):
                self._control(json.loads(frame))
            elif frame and frame[0] == MESSAGE_DATA:
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                channel = self.channels.get(self._subscriptions.get(sub, -1))
                if channel is None:
                    continue
                try:
                    self._messages.put_nowait(Message(channel, log_time, bytes(frame[13:])))
                except asyncio.QueueFull:
                    self.dropped += 1

    def _control(self, message: dict[str, Any]) -> None:
        op = message.get("op")
        if op == "advertise":
            for c in message.get("channels", []):
                schema = c.get("schema", "")
                encoding = c.get("schemaEncoding") or ""
                # Binary schemas (protobuf's FileDescriptorSet) travel base64-encoded, text ones as text.
                raw = (
                    base64.b64decode(schema)
                    if encoding in ("protobuf", "flatbuffer", "ros2idl_binary")
                    or (c.get("encoding") == "protobuf" and not encoding)
                    else schema.encode()
                )
                self.channels[c["id"]] = Channel(
                    c["id"], c["topic"], c.get("encoding", ""), c.get("schemaName", ""), raw, encoding
                )
            self._advertised.set()
        elif op == "unadvertise":
            for cid in message.get("channelIds", []):
                self.channels.pop(cid, None)

    async def wait_for_topics(self, topics: Iterable[str], timeout: float = 10.0) -> dict[str, Channel]:
        """The advertised channels of these topics, once all of them are advertised."""
        wanted = set(topics)

        async def wait() -> dict[str, Channel]:
            while True:
                have = {c.topic: c for c in self.channels.values() if c.topic in wanted}
                if len(have) == len(wanted):
                    return have
                self._advertised.clear()
                await self._advertised.wait()

        return await asyncio.wait_for(wait(), timeout)

    async def subscribe(self, channels: Iterable[Channel]) -> None:
        subs = []
        for c in channels:
            sid = self._next_id
            self._next_id += 1
            self._subscriptions[sid] = c.id
            subs.append({"id": sid, "channelId": c.id})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def unsubscribe_all(self) -> None:
        ids = list(self._subscriptions)
        self._subscriptions.clear()
        await self.ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": ids}))

    async def messages(self) -> AsyncIterator[Message]:
        while True:
            yield await self._messages.get()

    async def next_message(self, timeout: float = 10.0) -> Message:
        return await asyncio.wait_for(self._messages.get(), timeout)

    async def advertise(
        self, topic: str, encoding: str, schema_name: str, schema: bytes = b"", schema_encoding: str = ""
    ) -> int:
        """Advertise a channel this client publishes on (the server must offer clientPublish)."""
        if "clientPublish" not in self.server_info.get("capabilities", []):
            raise ConnectionError("this live view takes no published channels (no clientPublish)")
        cid = self._next_id
        self._next_id += 1
        channel: dict[str, Any] = {"id": cid, "topic": topic, "encoding": encoding, "schemaName": schema_name}
        if schema:
            channel["schema"] = base64.b64encode(schema).decode() if schema_encoding == "protobuf" else schema.decode()
            channel["schemaEncoding"] = schema_encoding
        await self.ws.send(json.dumps({"op": "advertise", "channels": [channel]}))
        return cid

    async def publish(self, channel_id: int, data: bytes) -> None:
        await self.ws.send(struct.pack("<BI", CLIENT_MESSAGE_DATA, channel_id) + data)
