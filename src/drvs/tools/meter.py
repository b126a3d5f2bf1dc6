"""A TCP relay that counts the bytes it carries: TCP payload, and what an Ethernet link would carry.

Two figures, both directions:

- **payload**: the bytes `read()` returns, i.e. what the applications wrote (HTTP/2 frames for gRPC);
- **wire**: the frames a 1500-byte-MTU Ethernet link would carry for the same connection. Each of
  the relay's sockets is opened with TCP_MAXSEG 1460 (1500 - 20 IPv4 - 20 TCP), so the kernel cuts
  its TCP stream, and the peer's, into Ethernet-sized segments (1448 bytes of payload once the 12
  bytes of the timestamp option are taken off), even on loopback (MTU 64 kB). When a connection
  closes (and whenever `wire()` is asked), the kernel's per-socket counters (`TCP_INFO`:
  `tcpi_segs_out`, `tcpi_segs_in`, `tcpi_bytes_sent`, `tcpi_bytes_received`) give every segment
  each way, pure ACKs, SYN and FIN included, and the payload they carried. Wire bytes are that
  payload plus, per segment, 14 bytes of Ethernet header, 20 of IPv4 and 20 of TCP (32 when the
  connection uses timestamps, as Linux does by default): 66 bytes. Not counted: the preamble,
  frame check sequence and inter-frame gap of the physical layer, and the larger TCP options of
  the two SYNs.

Which socket is measured: `side="client"` counts the connection between the relay and whoever
dialled it (a robot in front of a server), `side="target"` the one between the relay and its target
(a robot's listener, which cameras dial). The payload figures are the same on both.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from dataclasses import astuple, dataclass
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from drvs.robot import DrvsClient

_CHUNK = 65536

#: TCP_MAXSEG on every relay socket: a 1500-byte IPv4 MTU less 20 bytes of IP and 20 of TCP. Linux
#: takes the options the connection uses (12 bytes of timestamps) off it: 1448 payload bytes a segment.
ETHERNET_MSS = 1460
ETHERNET_HEADER = 14
IPV4_HEADER = 20
TCP_HEADER = 20
TCP_TIMESTAMPS = 12
_TCPI_OPT_TIMESTAMPS = 1
# struct tcp_info (linux/tcp.h): tcpi_options is byte 5; tcpi_bytes_acked and tcpi_bytes_received
# (u64) at 120 and 128; tcpi_segs_out and tcpi_segs_in (u32) at 136 and 140; tcpi_bytes_sent
# (u64, Linux 5.5+, retransmissions included) at 200.
_OFF_OPTIONS = 5
_OFF_BYTES_ACKED = 120
_OFF_SEGS = 136
_OFF_BYTES_SENT = 200
_TCP_INFO_LEN = 256


@dataclass(frozen=True)
class TcpCounters:
    """The kernel's counters of one TCP socket, from its own side: out = sent by this socket."""

    payload_out: int
    payload_in: int
    segments_out: int
    segments_in: int
    timestamps: bool

    @property
    def header_bytes(self) -> int:
        """Ethernet + IPv4 + TCP header bytes of one of this connection's segments."""
        return ETHERNET_HEADER + IPV4_HEADER + TCP_HEADER + (TCP_TIMESTAMPS if self.timestamps else 0)

    @property
    def wire_out(self) -> int:
        return self.payload_out + self.segments_out * self.header_bytes

    @property
    def wire_in(self) -> int:
        return self.payload_in + self.segments_in * self.header_bytes


def tcp_counters(sock: socket.socket) -> TcpCounters:
    """Read a connected TCP socket's TCP_INFO (Linux). Raises OSError if the socket is closed or the
    kernel does not give the counters (before Linux 4.2)."""
    raw = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, _TCP_INFO_LEN)
    if len(raw) < _OFF_SEGS + 8:
        raise OSError(f"TCP_INFO: {len(raw)} bytes, too short for segment counters (Linux >= 4.2 needed)")
    acked, received = struct.unpack_from("=QQ", raw, _OFF_BYTES_ACKED)
    segs_out, segs_in = struct.unpack_from("=II", raw, _OFF_SEGS)
    sent = struct.unpack_from("=Q", raw, _OFF_BYTES_SENT)[0] if len(raw) >= _OFF_BYTES_SENT + 8 else acked
    return TcpCounters(sent, received, segs_out, segs_in, bool(raw[_OFF_OPTIONS] & _TCPI_OPT_TIMESTAMPS))


def ethernet_socket(family: socket.AddressFamily = socket.AF_INET) -> socket.socket:
    """A non-blocking TCP socket whose segments are Ethernet-sized (TCP_MAXSEG, set before connecting
    or listening, so the MSS it announces holds its peer to the same size)."""
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, ETHERNET_MSS)
        sock.setblocking(False)
    except BaseException:
        sock.close()
        raise
    return sock


async def _resolve(host: str, port: int) -> tuple[socket.AddressFamily, tuple[str, int]]:
    infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM)
    if not infos:
        raise OSError(f"cannot resolve {host}:{port}")
    family, _, _, _, address = infos[0]
    return family, (str(address[0]), int(address[1]))


@dataclass(frozen=True)
class WireCount:
    """Bytes to and from the measured host as a 1500-byte-MTU Ethernet link carries them (`to_host` is
    what the relay sent it, `from_host` what it sent), their segments, and the TCP payload in them, all
    from the kernel's counters of the socket that faces the host."""

    to_host: int = 0
    from_host: int = 0
    segments_to_host: int = 0
    segments_from_host: int = 0
    payload_to_host: int = 0
    payload_from_host: int = 0

    @property
    def total(self) -> int:
        return self.to_host + self.from_host

    @property
    def segments(self) -> int:
        return self.segments_to_host + self.segments_from_host

    @property
    def payload(self) -> int:
        return self.payload_to_host + self.payload_from_host

    def __add__(self, other: WireCount) -> WireCount:
        return WireCount(*(a + b for a, b in zip(astuple(self), astuple(other), strict=True)))

    def __sub__(self, other: WireCount) -> WireCount:
        return WireCount(*(a - b for a, b in zip(astuple(self), astuple(other), strict=True)))


class _Measured:
    """The measured socket of one relayed connection and the last counters read from it (the socket
    itself is gone once the connection closes)."""

    def __init__(self, sock: socket.socket | None) -> None:
        self._sock = sock
        self.last = WireCount()

    def read(self) -> WireCount:
        if self._sock is not None:
            try:
                c = tcp_counters(self._sock)
            except (OSError, ValueError):  # closed: keep the last reading
                self._sock = None
            else:
                self.last = WireCount(c.wire_out, c.wire_in, c.segments_out, c.segments_in, c.payload_out, c.payload_in)
        return self.last


class CountingRelay:
    """Accepts connections on a local port and forwards each to `target`, counting both directions.

    The target may be set after start() (set_target); connections wait for it. With bucket_s, the
    payload bytes (`timeline`) and the wire bytes (`wire_timeline`) carried, both directions, are
    also kept per interval since start, for plots.
    """

    def __init__(
        self,
        target_host: str | None = None,
        target_port: int = 0,
        listen_host: str = "127.0.0.1",
        bucket_s: float = 0.0,
        side: Literal["client", "target"] = "client",
    ) -> None:
        if side not in ("client", "target"):
            raise ValueError(f"side: {side!r} must be 'client' or 'target'")
        self.target: tuple[str, int] | None = None
        self._target_known = asyncio.Event()
        if target_host is not None:
            self.set_target(target_host, target_port)
        self.listen_host = listen_host
        self.side = side
        self.port = 0
        self.to_target = 0
        self.from_target = 0
        self.bucket_s = bucket_s
        self.timeline: dict[int, int] = {}
        self.wire_timeline: dict[int, int] = {}
        self._t0 = 0.0
        self._server: asyncio.Server | None = None
        self._pipes: set[asyncio.Task[None]] = set()
        self._measured: list[_Measured] = []
        self._sampler: asyncio.Task[None] | None = None
        self._sampled = 0

    def set_target(self, host: str, port: int) -> None:
        self.target = (host, port)
        self._target_known.set()

    @property
    def total(self) -> int:
        """Payload bytes carried, both directions."""
        return self.to_target + self.from_target

    def wire(self) -> WireCount:
        """Wire bytes and segments on the measured side of every connection so far (open ones read now)."""
        count = WireCount()
        for m in self._measured:
            count = count + m.read()
        return count

    async def start(self) -> int:
        loop = asyncio.get_running_loop()
        self._t0 = loop.time()
        family, address = await _resolve(self.listen_host, 0)
        listener = ethernet_socket(family)
        try:
            listener.bind(address)
        except BaseException:
            listener.close()
            raise
        self._server = await asyncio.start_server(self._accept, sock=listener)
        self.port = int(self._server.sockets[0].getsockname()[1])
        if self.bucket_s:
            self._sampler = loop.create_task(self._sample())
        return self.port

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            for task in list(self._pipes):
                task.cancel()
            await asyncio.gather(*self._pipes, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None
        if self._sampler is not None:
            self._sampler.cancel()
            await asyncio.gather(self._sampler, return_exceptions=True)
            self._sampler = None
            self._sample_now()

    def _bucket(self) -> int:
        return int((asyncio.get_running_loop().time() - self._t0) / self.bucket_s)

    def _sample_now(self) -> None:
        total = self.wire().total
        k = self._bucket()
        self.wire_timeline[k] = self.wire_timeline.get(k, 0) + total - self._sampled
        self._sampled = total

    async def _sample(self) -> None:
        """Reads the counters at the end of every bucket: the wire bytes of each interval."""
        loop = asyncio.get_running_loop()
        k = 0
        while True:
            k += 1
            await asyncio.sleep(max(0.0, self._t0 + k * self.bucket_s - loop.time()))
            self._sample_now()

    async def _accept(self, client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        try:
            await self._target_known.wait()
            assert self.target is not None
            family, address = await _resolve(*self.target)
            upstream = ethernet_socket(family)
            try:
                await asyncio.get_running_loop().sock_connect(upstream, address)
            except BaseException:
                upstream.close()
                raise
            target_r, target_w = await asyncio.open_connection(sock=upstream)
        except OSError:
            client_w.close()
            return
        measured = _Measured((client_w if self.side == "client" else target_w).get_extra_info("socket"))
        self._measured.append(measured)
        up = asyncio.get_running_loop().create_task(self._pipe(client_r, target_w, True, measured))
        down = asyncio.get_running_loop().create_task(self._pipe(target_r, client_w, False, measured))
        for task in (up, down):
            self._pipes.add(task)
            task.add_done_callback(self._pipes.discard)
        await asyncio.gather(up, down, return_exceptions=True)

    async def _pipe(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, upstream: bool, measured: _Measured
    ) -> None:
        try:
            loop = asyncio.get_running_loop()
            while data := await reader.read(_CHUNK):
                if upstream:
                    self.to_target += len(data)
                else:
                    self.from_target += len(data)
                if self.bucket_s:
                    k = int((loop.time() - self._t0) / self.bucket_s)
                    self.timeline[k] = self.timeline.get(k, 0) + len(data)
                writer.write(data)
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            measured.read()  # the last look at the counters before a socket of the pair closes
            with contextlib.suppress(Exception):
                writer.close()


class MeteredClient:
    """A plain DrvsClient whose two connections pass through counting relays, for benchmarks and
    the simulated robot (robot code never needs it).

    One relay stands in front of each server given (a list: "a:50051,b:50051"): the client dials
    them (`server=` the relays' addresses, in the same order), and their bytes are added up.
    The other stands in front of the robot's report listener: cameras dial it (`advertise=` its
    address), and it forwards to the listener once the listener has its port. Its measured side is
    the socket to the listener (side="target"), as the robot's own socket would see it.

        async with MeteredClient(server, robot_id="sim-robot") as metered:
            await metered.client.detect(...)
            received, sent = metered.payload_bytes()

    `listen_host`: where the callback relay and the listener bind (default: the local address that
    reaches the server); the other keyword arguments are DrvsClient's.
    """

    def __init__(self, server: str, *, listen_host: str | None = None, **client_args: Any) -> None:
        from drvs.core.net import parse_address, parse_address_list

        self.server = server
        self._targets = [parse_address(a, "server") for a in parse_address_list(server, "server")]
        self._listen_host = listen_host
        self._client_args = client_args
        self.client: DrvsClient | None = None
        self._callback: CountingRelay | None = None
        self._server_relays: list[CountingRelay] = []

    async def start(self) -> DrvsClient:
        """Start both relays and the client behind them; returns the (started, unchecked) client."""
        from drvs.core.net import format_address, local_ip_towards
        from drvs.robot import DrvsClient

        host = self._listen_host
        if host is None:
            host = await asyncio.to_thread(local_ip_towards, self.server)
        self._callback = CountingRelay(listen_host=host, side="target")
        await self._callback.start()
        for target in self._targets:
            relay = CountingRelay(*target)
            self._server_relays.append(relay)
            await relay.start()
        client = DrvsClient(
            ",".join(format_address("127.0.0.1", relay.port) for relay in self._server_relays),
            listen=format_address(host, 0),
            advertise=format_address(host, self._callback.port),
            **self._client_args,
        )
        self.client = client
        await client.start()
        self._callback.set_target(host, client.port)
        return client

    def _relays(self) -> tuple[CountingRelay, list[CountingRelay]]:
        if self._callback is None or not self._server_relays:
            raise RuntimeError("MeteredClient is not started")
        return self._callback, self._server_relays

    def payload_bytes(self) -> tuple[int, int]:
        """(received, sent) TCP payload bytes on the robot's connections."""
        callback, servers = self._relays()
        return (
            callback.to_target + sum(s.from_target for s in servers),
            callback.from_target + sum(s.to_target for s in servers),
        )

    def ethernet_bytes(self) -> tuple[int, int]:
        """(received, sent) bytes on the robot's connections as a 1500-byte-MTU Ethernet link
        carries them: payload plus Ethernet, IP and TCP headers of every segment, ACKs included."""
        callback, servers = self._relays()
        wire = callback.wire()
        for relay in servers:
            wire = wire + relay.wire()
        return wire.to_host, wire.from_host

    async def close(self) -> None:
        """Close the client, then both relays."""
        if self.client is not None:
            await self.client.close()
        for relay in (self._callback, *self._server_relays):
            if relay is not None:
                await relay.close()

    async def __aenter__(self) -> MeteredClient:
        try:
            await self.start()
        except BaseException:
            await self.close()
            raise
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()
