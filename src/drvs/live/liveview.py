"""The live view and recordings (pip install 'drvs[live]'), through the ecosystem's own libraries:
a Foxglove WebSocket server and MCAP files from `foxglove-sdk`, protobuf schemas embedded with
`mcap-protobuf-support`.

A `LiveHub` is one foxglove-sdk context with up to two sinks: a WebSocket server (`--foxglove
HOST:PORT`, which Foxglove opens as ws://HOST:PORT) and an MCAP writer (`--record FILE.mcap`,
chunked and zstd-compressed). Every channel logged to it reaches both. The scene is in the `map`
frame: the floor's own metres, x east and y north, z up.

The hub also takes channels that WebSocket clients advertise (Foxglove's clientPublish): a robot
publishes its pose and paths into the same view and recording (drvs.live.foxglove_client). What it takes
is shown and recorded, nothing more: DRVS never acts on it. Each client channel is a channel of its
own (metadata `published_by: client N`, never one of the hub's, whatever its topic), closed when the
client unadvertises it or leaves; topics under `/drvs/` are the hub's alone (`RESERVED`), a client
has at most `MAX_CLIENT_CHANNELS`, and its messages count against the hub's budget like any other.

What enters the hub is bounded (`admit`): no message over `MAX_MESSAGE_BYTES`, and at most
`bytes_per_s` a second on average (bursts of two seconds' worth): beyond that it is dropped and
counted, so a flood grows neither the recording nor the memory behind it faster than that.

Topic names and schemas are listed in docs/operations.md ("Live view and recordings")."""

from __future__ import annotations

import importlib.util
import itertools
import json
import logging
import math
import threading
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drvs.core._files import folder_problem
from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.net import is_loopback_host, parse_address

if TYPE_CHECKING:
    import foxglove
    from shapely.geometry import Polygon

log = logging.getLogger("drvs.live.liveview")

LIVE_INSTALL = "pip install 'drvs[live]'"
#: The modules the live extra installs (drvs.tools._entry.EXTRAS["live"] names the same).
LIVE_MODULES = ("foxglove", "mcap", "mcap_protobuf")
FRAME = "map"
#: Target uncompressed size of a recording's chunks: about a second of an office's messages.
CHUNK_BYTES = 256 * 1024
#: Messages a slow WebSocket client may fall behind by before the oldest are dropped for it.
CLIENT_BACKLOG = 1024
#: What a client may publish into the view (clientPublish): the encodings Foxglove itself sends.
CLIENT_ENCODINGS = ["protobuf", "json"]
#: Topics under this prefix are the hub's own: no client may publish on them.
RESERVED = "/drvs/"
#: Channels one client may have advertised at once.
MAX_CLIENT_CHANNELS = 16
#: No message larger than this is shown or recorded (a client's schema neither).
MAX_MESSAGE_BYTES = 1 << 20
#: What may enter the hub a second, on average (bytes, before compression); bursts of twice that.
BYTES_PER_S = 8 << 20


class ByteBudget:
    """A token bucket of bytes (thread-safe): `take(n)` is True while the average stays under
    `rate` a second, with bursts up to `burst`."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate = rate
        self.burst = burst
        self._level = burst
        self._at = time.monotonic()
        self._lock = threading.Lock()

    def take(self, n: int) -> bool:
        with self._lock:
            now = time.monotonic()
            self._level = min(self.burst, self._level + (now - self._at) * self.rate)
            self._at = now
            if n > self._level:
                return False
            self._level -= n
            return True


def require(flag: str) -> None:
    """Raise FailedPrecondition naming the extra when the live view's libraries are missing."""
    for name in LIVE_MODULES:
        if importlib.util.find_spec(name) is None:
            raise FailedPrecondition(
                f"{flag}: needs the live view and recordings: {LIVE_INSTALL} (no module named {name!r})"
            )


def parse_listen(text: str, flag: str, *, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """HOST:PORT (or PORT alone, on `default_host`) where a live view listens; port 0 picks one."""
    text = text.strip()
    if text.isdigit():
        text = f"{default_host}:{text}"
    return parse_address(text, flag, allow_port_zero=True)


def proto_schema(message_class: Any) -> foxglove.Schema:
    """A protobuf message class's schema as MCAP and Foxglove carry it: its full name and a
    FileDescriptorSet of its file and every file it imports, so any tool decodes it alone."""
    import foxglove
    from mcap_protobuf.schema import build_file_descriptor_set

    return foxglove.Schema(
        name=message_class.DESCRIPTOR.full_name,
        encoding="protobuf",
        data=build_file_descriptor_set(message_class).SerializeToString(),
    )


class _Relay:
    """Takes the channels WebSocket clients advertise and logs what they publish on a channel of
    their own with the same topic, encoding and schema (so it is seen by every client and recorded),
    tagged with the client's id; refuses the hub's own topics (`RESERVED`) and more than
    `MAX_CLIENT_CHANNELS` a client, and closes a client's channels when it unadvertises or leaves."""

    def __init__(self, hub: LiveHub) -> None:
        self._hub = hub
        self._lock = threading.Lock()
        self._channels: dict[tuple[int, int], Any] = {}

    # foxglove-sdk calls these from its own threads.
    def on_client_advertise(self, client: Any, channel: Any) -> None:
        import foxglove

        refused = self._refusal(client, channel)
        if refused:
            log.warning("live view: client %s may not publish %r: %s", client.id, channel.topic[:80], refused)
            return
        schema = None
        if channel.schema_name:
            schema = foxglove.Schema(
                name=channel.schema_name, encoding=channel.schema_encoding or "", data=bytes(channel.schema or b"")
            )
        own = foxglove.Channel(
            channel.topic,
            message_encoding=channel.encoding,
            schema=schema,
            metadata={"published_by": f"client {client.id}"},
            context=self._hub.context,
        )
        with self._lock:
            old = self._channels.pop((client.id, channel.id), None)
            self._channels[(client.id, channel.id)] = own
        if old is not None:
            old.close()
        log.info("live view: client %s publishes %s (%s)", client.id, channel.topic, channel.schema_name)

    def _refusal(self, client: Any, channel: Any) -> str:
        if channel.topic.startswith(RESERVED) or not channel.topic.startswith("/"):
            return f"topics under {RESERVED} are the server's own, and a topic starts with '/'"
        if len(channel.schema or b"") > MAX_MESSAGE_BYTES:
            return f"its schema is over {MAX_MESSAGE_BYTES} bytes"
        with self._lock:
            if sum(1 for k in self._channels if k[0] == client.id) >= MAX_CLIENT_CHANNELS:
                return f"it already publishes {MAX_CLIENT_CHANNELS} channels"
        return ""

    def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
        with self._lock:
            channel = self._channels.pop((client.id, client_channel_id), None)
        if channel is not None:
            channel.close()

    def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
        with self._lock:
            channel = self._channels.get((client.id, client_channel_id))
        if channel is not None and self._hub.admit(len(data)):
            channel.log(data)

    def on_client_disconnect(self, client: Any) -> None:
        with self._lock:
            gone = [self._channels.pop(k) for k in [k for k in self._channels if k[0] == client.id]]
        for channel in gone:
            channel.close()

    def __getattr__(self, name: str) -> Any:
        # The SDK's listener protocol grows (parameters, services, playback...): none of them here.
        if name.startswith("on_"):
            return lambda *args, **kwargs: None
        raise AttributeError(name)


class LiveHub:
    """One foxglove-sdk context and its sinks: `listen` (host, port) for a WebSocket server, `record`
    a new MCAP file. Channels come from `channel`, `proto_channel` and `scene_channel`; log to them
    from any thread. `close()` stops the server and finishes the file (its summary and index).

    The server: `accept_clients` offers clientPublish (what clients publish is relayed onto the
    hub), `capabilities` more of Foxglove's (e.g. `time`), `listener` a foxglove ServerListener of
    one's own instead of the relay, `backlog` messages per client before the oldest are dropped,
    `token` one a WebSocket must present (drvs.live.liveview_gate). Listening beyond loopback is warned
    about at start (unless `warn` is False), loudest without a token. `bytes_per_s`: what `admit`
    lets in (see the module)."""

    def __init__(
        self,
        name: str,
        *,
        listen: tuple[str, int] | None = None,
        record: Path | None = None,
        accept_clients: bool = False,
        tls: tuple[bytes, bytes] | None = None,
        capabilities: Sequence[Any] = (),
        listener: Any = None,
        backlog: int = CLIENT_BACKLOG,
        token: str | None = None,
        bytes_per_s: float = BYTES_PER_S,
        warn: bool = True,
    ) -> None:
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions
        from foxglove.websocket import Capability

        self.context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.server: Any = None
        self.gate: Any = None
        self.writer: Any = None
        self.record = record
        self.budget = ByteBudget(bytes_per_s, 2 * bytes_per_s)
        #: Messages `admit` turned away (over MAX_MESSAGE_BYTES, or beyond the budget).
        self.dropped = 0
        if record is not None:
            if (problem := folder_problem(record.parent)) is not None:
                raise InvalidArgument(f"--record: cannot write {record}: {record.parent}: {problem}")
            try:
                record.parent.mkdir(parents=True, exist_ok=True)
                self.writer = foxglove.open_mcap(
                    record,
                    allow_overwrite=True,
                    context=self.context,
                    writer_options=MCAPWriteOptions(
                        compression=MCAPCompression.Zstd, chunk_size=CHUNK_BYTES, profile="", compression_threads=0
                    ),
                )
            except Exception as exc:
                raise InvalidArgument(f"--record: cannot write {record}: {exc}") from exc
        if listen is not None:
            host, port = listen
            try:
                self.server = foxglove.start_server(
                    name=name,
                    host="127.0.0.1" if token else host,
                    port=0 if token else port,
                    context=self.context,
                    capabilities=[*([Capability.ClientPublish] if accept_clients else []), *capabilities],
                    supported_encodings=CLIENT_ENCODINGS if accept_clients else None,
                    server_listener=listener if listener is not None else _Relay(self),
                    message_backlog_size=backlog,
                    tls_cert=tls[0] if tls else None,
                    tls_key=tls[1] if tls else None,
                )
                if token:
                    from drvs.live.liveview_gate import TokenGate

                    self.gate = TokenGate(host, port, self.server.port, token)
            except Exception as exc:
                self.close()
                raise InvalidArgument(f"--foxglove: cannot listen on {host}:{port}: {exc}") from exc
            self.url = f"{'wss' if tls else 'ws'}://{host}:{self.port}"
            if warn:  # (drvs-camera says it in its own words)
                _warn_beyond_loopback(name, host, self.url, bool(token))

    @property
    def port(self) -> int:
        if self.gate is not None:
            return int(self.gate.port)
        return int(self.server.port) if self.server is not None else 0

    def admit(self, nbytes: int) -> bool:
        """Whether a message of `nbytes` may enter the hub (shown and recorded): at most
        MAX_MESSAGE_BYTES, within the hub's bytes a second. Turned away: counted in `dropped`."""
        if nbytes <= MAX_MESSAGE_BYTES and self.budget.take(nbytes):
            return True
        with self._lock:
            self.dropped += 1
        return False

    def channel_for(self, topic: str, encoding: str, schema: Any, metadata: dict[str, str] | None = None) -> Any:
        """The hub's channel for `topic` (made on first use; a topic keeps its first schema)."""
        import foxglove

        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                channel = foxglove.Channel(
                    topic, message_encoding=encoding, schema=schema, metadata=metadata, context=self.context
                )
                self._channels[topic] = channel
            return channel

    def proto_channel(self, topic: str, message_class: Any) -> Any:
        """A channel of one of DRVS's own protobuf messages (drvs.v1.*), its schema embedded."""
        return self.channel_for(topic, "protobuf", proto_schema(message_class))

    def scene_channel(self, topic: str) -> Any:
        from foxglove.channels import SceneUpdateChannel

        with self._lock:
            channel = self._channels.get(topic)
            if channel is None:
                channel = SceneUpdateChannel(topic, context=self.context)
                self._channels[topic] = channel
            return channel

    def close(self) -> None:
        if self.gate is not None:
            self.gate.close()
            self.gate = None
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def _warn_beyond_loopback(name: str, host: str, url: str, token: bool) -> None:
    if is_loopback_host(host):
        return
    if token:
        log.warning(
            "%s: the live view on %s is reachable beyond this host; it takes only connections with its token, "
            "but ws:// is plain text: keep it on a network nobody else reads",
            name,
            url,
        )
    else:
        log.warning(
            "%s: THE LIVE VIEW ON %s IS OPEN TO ANYONE WHO REACHES IT: they see the building, every request and "
            "detection, and may publish into the view and the recording. Listen on 127.0.0.1 (and reach it "
            "through an SSH tunnel), or give drvs-server's view a token (--foxglove-token)",
            name,
            url,
        )


# --- scene entities (foxglove.SceneUpdate) ---------------------------------------------------------


def rgba(r: float, g: float, b: float, a: float = 1.0) -> Any:
    from foxglove.messages import Color

    return Color(r=r, g=g, b=b, a=a)


def stamp(t: float | None = None) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp.from_epoch_secs(time.time() if t is None else t)


def _points(coords: Iterable[Sequence[float]], z: float) -> list[Any]:
    from foxglove.messages import Point3

    return [Point3(x=float(c[0]), y=float(c[1]), z=z) for c in coords]


def line(
    coords: Iterable[Sequence[float]], color: Any, *, z: float = 0.02, loop: bool = False, width: float = 0.04
) -> Any:
    from foxglove.messages import LinePrimitive, LinePrimitiveLineType

    return LinePrimitive(
        type=LinePrimitiveLineType.LineLoop if loop else LinePrimitiveLineType.LineStrip,
        thickness=width,
        points=_points(coords, z),
        color=color,
    )


def fill(polygon: Polygon, color: Any, *, z: float = 0.01) -> Any | None:
    """The polygon's area as triangles (shapely's constrained Delaunay: holes and concave outlines
    stay as drawn), at height z; None for an empty polygon."""
    import shapely
    from foxglove.messages import TriangleListPrimitive

    if polygon.is_empty or polygon.area <= 0:
        return None
    points: list[Any] = []
    for triangle in shapely.get_parts(shapely.constrained_delaunay_triangles(polygon)):
        points += _points(list(triangle.exterior.coords)[:3], z)
    return TriangleListPrimitive(points=points, color=color) if points else None


def text(label: str, x: float, y: float, color: Any, *, z: float = 0.3, size: float = 14.0) -> Any:
    from foxglove.messages import Pose, Quaternion, TextPrimitive, Vector3

    return TextPrimitive(
        pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=0, y=0, z=0, w=1)),
        billboard=True,
        font_size=size,
        scale_invariant=True,
        color=color,
        text=label,
    )


def outlines(geometry: Any) -> list[Polygon]:
    """The polygons of a shapely geometry (one, or a multi-polygon's parts)."""
    import shapely

    return [g for g in shapely.get_parts(geometry) if g.geom_type == "Polygon" and not g.is_empty]


def area_entity(
    entity_id: str,
    geometry: Any,
    color: Any,
    *,
    edge: Any | None = None,
    label: str = "",
    z: float = 0.0,
    lifetime_s: float = 0.0,
    t: float | None = None,
    metadata: dict[str, str] | None = None,
    filled: bool = True,
) -> Any:
    """A flat area on the floor (a field of view, a region, a detection's outline): filled with
    `color`, outlined with `edge`, labelled at its centroid; gone after `lifetime_s` (0: until
    deleted or replaced by an entity of the same id). `filled` False: the outline alone (cheaper)."""
    from foxglove.messages import Duration, KeyValuePair, SceneEntity

    lines, triangles, texts = [], [], []
    for polygon in outlines(geometry):
        area = fill(polygon, color, z=z + 0.005) if filled else None
        if area is not None:
            triangles.append(area)
        lines.append(line(polygon.exterior.coords, edge or color, z=z + 0.01, loop=True))
    if label and not geometry.is_empty:
        c = geometry.centroid
        texts.append(text(label, c.x, c.y, edge or color, z=z + 0.3))
    return SceneEntity(
        timestamp=stamp(t),
        frame_id=FRAME,
        id=entity_id,
        lifetime=Duration.from_secs(lifetime_s) if lifetime_s > 0 else None,
        lines=lines,
        triangles=triangles,
        texts=texts,
        metadata=[KeyValuePair(key=k, value=v) for k, v in (metadata or {}).items()],
    )


def wall_entity(entity_id: str, polygon: Polygon, *, height: float = 1.0) -> Any:
    """A wall, desk or any solid of the floor plan: its outline extruded to `height`."""
    from foxglove.messages import SceneEntity, TriangleListPrimitive

    grey = rgba(0.55, 0.57, 0.6, 0.9)
    sides: list[Any] = []
    coords = list(polygon.exterior.coords)
    for (x0, y0), (x1, y1) in itertools.pairwise(coords):
        quad = [(x0, y0, 0.0), (x1, y1, 0.0), (x1, y1, height), (x0, y0, 0.0), (x1, y1, height), (x0, y0, height)]
        sides += [_points([(x, y)], z)[0] for x, y, z in quad]
    prims = [TriangleListPrimitive(points=sides, color=grey)]
    top = fill(polygon, rgba(0.45, 0.47, 0.5, 1.0), z=height)
    if top is not None:
        prims.append(top)
    return SceneEntity(
        timestamp=stamp(),
        frame_id=FRAME,
        id=entity_id,
        triangles=prims,
        lines=[line(coords, rgba(0.2, 0.2, 0.25), z=height + 0.005, loop=True, width=0.03)],
    )


def deletion(entity_id: str) -> Any:
    from foxglove.messages import SceneEntityDeletion, SceneEntityDeletionType

    return SceneEntityDeletion(timestamp=stamp(), type=SceneEntityDeletionType.MatchingId, id=entity_id)


def scene(entities: Sequence[Any] = (), deletions: Sequence[Any] = ()) -> Any:
    from foxglove.messages import SceneUpdate

    return SceneUpdate(entities=list(entities), deletions=list(deletions))


def palette(key: str, alpha: float = 1.0) -> Any:
    """A steady colour per id (a camera's, a track's): the same in every run and viewer."""
    h = sum((i + 1) * ord(ch) for i, ch in enumerate(key)) % 360 / 360.0
    import colorsys

    r, g, b = colorsys.hsv_to_rgb(h, 0.65, 0.95)
    return rgba(r, g, b, alpha)


def heading_quaternion(yaw: float) -> Any:
    from foxglove.messages import Quaternion

    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


# --- the layout shipped in docs/foxglove-layout.json -------------------------------------------------

#: The topics a 3D panel shows, in drawing order.
SCENE_TOPICS = ("/drvs/floor_plan", "/drvs/cameras", "/drvs/requests", "/drvs/detections", "/drvs/tracks")
ROBOT_TOPICS = ("/robot/paths",)


def foxglove_layout() -> str:
    """A Foxglove layout (foxglove-sdk's own `foxglove.layouts`): a 3D panel on the map frame,
    looking down on the floor, with every scene topic and the robot on, beside the raw replies.
    docs/foxglove-layout.json is this, written by `python -m drvs.live.liveview > docs/foxglove-layout.json`
    (tests/live/test_liveview.py checks the two agree)."""
    import foxglove.layouts as fl

    topics: dict[str, Any] = {t: fl.BaseRendererSceneUpdateTopicSettings(visible=True) for t in SCENE_TOPICS}
    topics |= {t: fl.BaseRendererSceneUpdateTopicSettings(visible=True) for t in ROBOT_TOPICS}
    topics["/robot/pose"] = fl.BaseRendererPoseTopicSettings(visible=True, type="arrow")
    three_d = fl.ThreeDeePanel(
        title="DRVS: the building",
        config=fl.ThreeDeeConfig(
            fixed_frame=FRAME,
            follow_tf=FRAME,
            topics=topics,
            camera_state=fl.ThreeDeeCameraState(
                distance=30.0, perspective=True, phi=30.0, target=(10.0, 5.0, 0.0), theta_offset=0.0
            ),
        ),
    )
    replies = fl.RawMessagesPanel(title="replies", config=fl.RawMessagesConfig(topic_path="/drvs/rpc/replies"))
    layout = fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[fl.SplitItem(proportion=3, content=three_d), fl.SplitItem(proportion=1, content=replies)],
        )
    )
    return json.dumps(json.loads(layout.to_json()), indent=1) + "\n"


if __name__ == "__main__":
    print(foxglove_layout(), end="")
