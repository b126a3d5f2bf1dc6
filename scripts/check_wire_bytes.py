"""One-off check of drvs.tools.meter's wire bytes against a packet capture (root, tcpdump and ethtool needed).

In a fresh network namespace whose loopback has segmentation and receive offloads turned off (so
each TCP segment is one captured frame), a CountingRelay carries 200 small request/reply round trips
and a 1 MB transfer; tcpdump captures the relay's client-side connection. The script prints the
relay's wire figures (from TCP_INFO) beside the capture's frame count and bytes, each direction.

    sudo .venv/bin/python scripts/check_wire_bytes.py [--offloads on]

Not a test: it needs root and tcpdump. docs/benchmarks.md gives its result.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BULK = 1_000_000


async def exchange() -> None:
    from drvs.tools.meter import CountingRelay

    async def target(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        while data := await r.read(65536):
            w.write(b"z" * BULK if data.startswith(b"BULK") else b"r" * 300)
            await w.drain()
        w.close()

    server = await asyncio.start_server(target, "127.0.0.1", 0)
    relay = CountingRelay("127.0.0.1", server.sockets[0].getsockname()[1])
    await relay.start()
    print(json.dumps({"relay_port": relay.port}), flush=True)
    r, w = await asyncio.open_connection("127.0.0.1", relay.port)
    for _ in range(200):
        w.write(b"q" * 120)
        await w.drain()
        await r.readexactly(300)
        await asyncio.sleep(0.005)
    w.write(b"BULK")
    await w.drain()
    await r.readexactly(BULK)
    w.close()
    await w.wait_closed()
    await asyncio.sleep(0.2)
    await relay.close()
    wire = relay.wire()
    print(
        json.dumps(
            {
                "to_client": [wire.segments_to_host, wire.to_host],
                "from_client": [wire.segments_from_host, wire.from_host],
            }
        )
    )
    server.close()


def capture_sums(pcap: Path, port: int) -> dict[str, list[int]]:
    """Frames and their bytes to and from the relay's listening port, from a pcap file."""
    data = pcap.read_bytes()
    out = {"to_client": [0, 0], "from_client": [0, 0]}
    off = 24
    while off < len(data):
        _, _, incl, orig = struct.unpack_from("<IIII", data, off)
        frame = data[off + 16 : off + 16 + incl]
        off += 16 + incl
        ihl = (frame[14] & 15) * 4
        sport, dport = struct.unpack_from(">HH", frame, 14 + ihl)
        if port in (sport, dport):
            key = "to_client" if sport == port else "from_client"
            out[key][0] += 1
            out[key][1] += orig
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--offloads", choices=["on", "off"], default="off", help="loopback TSO/GSO/GRO")
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.inner:
        asyncio.run(exchange())
        return 0
    ns = f"drvswire{os.getpid()}"
    subprocess.run(["ip", "netns", "add", ns], check=True)
    try:
        run = ["ip", "netns", "exec", ns]
        subprocess.run([*run, "ip", "link", "set", "lo", "up"], check=True)
        o = args.offloads
        subprocess.run([*run, "ethtool", "-K", "lo", "tso", o, "gso", o, "gro", o], check=False, capture_output=True)
        with tempfile.TemporaryDirectory() as tmp:
            pcap = Path(tmp) / "cap.pcap"
            dump = subprocess.Popen([*run, "tcpdump", "-i", "lo", "-s", "96", "-U", "-w", str(pcap), "tcp"])
            time.sleep(1)  # a one-off script: let tcpdump open the interface before traffic starts
            inner = subprocess.run(
                [*run, sys.executable, __file__, "--inner"], check=True, capture_output=True, text=True
            )
            time.sleep(1)
            dump.terminate()
            dump.wait()
            lines = inner.stdout.splitlines()
            port = json.loads(lines[0])["relay_port"]
            print(f"loopback offloads {o}")
            print("relay (TCP_INFO):", lines[1])
            print("capture:         ", json.dumps(capture_sums(pcap, port)))
    finally:
        subprocess.run(["ip", "netns", "del", ns], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
