"""CountingRelay: exact payload counts, and wire counts a 1500-byte-MTU Ethernet link would carry."""

from __future__ import annotations

import asyncio
import math

import pytest

from drvs.tools.meter import ETHERNET_HEADER, IPV4_HEADER, TCP_HEADER, TCP_TIMESTAMPS, CountingRelay, tcp_counters

UP = 1_000_000  # bytes the client sends through the relay
DOWN = 300_000  # bytes the target answers with
PAYLOAD_PER_SEGMENT = 1448  # 1500 - 20 IPv4 - 20 TCP - 12 timestamps


async def _exchange(relay: CountingRelay) -> None:
    """A client sends UP bytes through the relay, the target answers DOWN bytes and closes."""
    r, w = await asyncio.open_connection("127.0.0.1", relay.port)
    w.write(b"x" * UP)
    await w.drain()
    got = 0
    while data := await r.read(65536):
        got += len(data)
    assert got == DOWN
    w.close()
    await w.wait_closed()


@pytest.mark.parametrize("side", ["client", "target"])
async def test_relay_counts_payload_and_ethernet_segments(side: str) -> None:
    async def target(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await r.readexactly(UP)
        w.write(b"y" * DOWN)
        await w.drain()
        w.close()

    server = await asyncio.start_server(target, "127.0.0.1", 0)
    relay = CountingRelay("127.0.0.1", server.sockets[0].getsockname()[1], bucket_s=0.01, side=side)  # type: ignore[arg-type]
    await relay.start()
    try:
        await _exchange(relay)
    finally:
        await relay.close()
        server.close()
        await server.wait_closed()
    assert (relay.to_target, relay.from_target) == (UP, DOWN)  # payload, exactly
    wire = relay.wire()
    # The measured host is the client (it sent UP) or the target (it sent DOWN).
    sent, received = (UP, DOWN) if side == "client" else (DOWN, UP)
    segs_from, segs_to = wire.segments_from_host, wire.segments_to_host
    # Ethernet-sized segments, though loopback's MTU is 64 kB: at least one per 1448 bytes each way
    # (with 64 kB segments there would be a few dozen in all) ...
    assert segs_from >= math.ceil(sent / PAYLOAD_PER_SEGMENT)
    assert segs_to >= math.ceil(received / PAYLOAD_PER_SEGMENT)
    # ... and not many more: the other direction's ACKs, the handshake and the close.
    assert segs_from + segs_to <= 2 * math.ceil((UP + DOWN) / PAYLOAD_PER_SEGMENT)
    header = ETHERNET_HEADER + IPV4_HEADER + TCP_HEADER + TCP_TIMESTAMPS
    # The kernel's payload counts (a SYN and a FIN each count one sequence byte), and wire = payload
    # + 66 B a segment. What the relay sent the host is tcpi_bytes_sent, retransmissions included
    # (the wire carries them twice): on a loaded machine the peer's ACK can come late enough for a
    # tail loss probe to send the last segment again (a full run here once counted 1 160 bytes more,
    # a partial last segment), so that side may exceed by a few segments.
    assert abs(wire.payload_from_host - sent) <= 2
    assert -2 <= wire.payload_to_host - received <= 4 * PAYLOAD_PER_SEGMENT
    assert wire.from_host == wire.payload_from_host + header * segs_from
    assert wire.to_host == wire.payload_to_host + header * segs_to
    # The timelines add up to the totals.
    assert sum(relay.timeline.values()) == UP + DOWN
    assert sum(relay.wire_timeline.values()) == wire.total


async def test_tcp_counters_of_a_plain_socket_match_a_known_transfer() -> None:
    """The struct tcp_info offsets: a connection's own counters of a transfer of known size."""
    done = asyncio.get_running_loop().create_future()

    async def sink(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await r.readexactly(50_000)
        w.write(b"k" * 7000)
        await w.drain()
        done.set_result(None)
        await r.read()
        w.close()

    server = await asyncio.start_server(sink, "127.0.0.1", 0)
    r, w = await asyncio.open_connection("127.0.0.1", server.sockets[0].getsockname()[1])
    try:
        w.write(b"s" * 50_000)
        await done
        await r.readexactly(7000)
        c = tcp_counters(w.get_extra_info("socket"))
    finally:
        w.close()
        await w.wait_closed()
        server.close()
        await server.wait_closed()
    assert c.payload_out == 50_000 and c.payload_in == 7000
    assert c.segments_out >= 2 and c.segments_in >= 2 and c.timestamps


def test_relay_rejects_an_unknown_side() -> None:
    with pytest.raises(ValueError, match="side: 'robot'"):
        CountingRelay("127.0.0.1", 1, side="robot")  # type: ignore[arg-type]
