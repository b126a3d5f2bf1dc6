"""Hosts apart (issue 6): the server, a camera and a robot each in a network namespace of their own,
joined by veth pairs to a bridge in a fourth. Links are cut and restored under running processes;
the system must recover without restarting any of them.

Needs root and `ip` (iproute2), as CI has; without them this test fails, saying so.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import shutil
import sys
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import CAMERA_REGISTERED, SERVER_READY, ManagedProcess
from tests.helpers import CAM1_REGION, MAX_RANGE

ROLES = Path(__file__).parents[1] / "fakes" / "fault_roles.py"
LEASE_S = 2.0
#: Hosts on the bridge: 10.77.0.1 server, .2 camera, .3 robot (inside their own namespaces, so
#: these addresses never meet the machine's own networks).
HOSTS = {"srv": "10.77.0.1", "cam": "10.77.0.2", "rob": "10.77.0.3"}


async def ip(*args: str, check: bool = True) -> None:
    proc = await asyncio.create_subprocess_exec(
        "ip", *args, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE
    )
    _, err = await asyncio.wait_for(proc.communicate(), 10)
    if check and proc.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {err.decode().strip()}")


@dataclass
class Network:
    """Namespaces `<prefix>-srv`, `-cam`, `-rob`, and `-sw` holding bridge br0 with ports vsrv, vcam, vrob."""

    prefix: str

    def ns(self, role: str) -> str:
        return f"{self.prefix}-{role}"

    async def cut(self, role: str) -> None:
        """Unplug a host's cable at the switch."""
        await ip("-n", self.ns("sw"), "link", "set", f"v{role}", "down")

    async def restore(self, role: str) -> None:
        await ip("-n", self.ns("sw"), "link", "set", f"v{role}", "up")

    def process(self, role: str, name: str, command: str, *args: str) -> ManagedProcess:
        """A DRVS console script (or, for command 'fault_roles', tests/fakes/fault_roles.py) run in a namespace."""
        if command == "fault_roles":
            proc = ManagedProcess(name, [sys.executable, str(ROLES), *args])
        else:
            proc = ManagedProcess.entry_point(name, command, *args)
        proc.argv = ["ip", "netns", "exec", self.ns(role), *proc.argv]
        return proc


@pytest_asyncio.fixture
async def network() -> AsyncIterator[Network]:
    if shutil.which("ip") is None:
        pytest.fail("test_netns needs the `ip` command (iproute2): install it, e.g. apt-get install iproute2")
    if os.geteuid() != 0:
        pytest.fail("test_netns needs root to create network namespaces (CI runs as root)")
    net = Network(f"drvs{secrets.token_hex(3)}")
    created: list[str] = []
    try:
        for role in ("sw", *HOSTS):
            await ip("netns", "add", net.ns(role))
            created.append(net.ns(role))
        sw = net.ns("sw")
        await ip("-n", sw, "link", "add", "br0", "type", "bridge")
        await ip("-n", sw, "link", "set", "br0", "up")
        for role, address in HOSTS.items():
            await ip("-n", sw, "link", "add", f"v{role}", "type", "veth", "peer", "name", "eth0", "netns", net.ns(role))
            await ip("-n", sw, "link", "set", f"v{role}", "master", "br0")
            await ip("-n", sw, "link", "set", f"v{role}", "up")
            await ip("-n", net.ns(role), "addr", "add", f"{address}/24", "dev", "eth0")
            await ip("-n", net.ns(role), "link", "set", "eth0", "up")
            await ip("-n", net.ns(role), "link", "set", "lo", "up")
        yield net
    finally:
        for name in reversed(created):
            await ip("netns", "del", name, check=False)


def results(probe: ManagedProcess, start: int) -> list[dict[str, Any]]:
    return [json.loads(line[7:]) for line in probe.lines[start:] if line.startswith("RESULT ")]


async def wait_result(
    probe: ManagedProcess, ok: Callable[[dict[str, Any]], bool], timeout: float, what: str
) -> dict[str, Any]:
    """The first result the probe robot prints from now on that satisfies `ok`."""
    start = len(probe.lines)

    def satisfying(line: str) -> dict[str, Any] | None:
        if not line.startswith("RESULT "):
            return None
        result: dict[str, Any] = json.loads(line[7:])
        return result if ok(result) else None

    try:
        return await probe.wait_for(satisfying, f"printing a result {what}", timeout, start)
    except RuntimeError:
        raise AssertionError(f"the probe robot exited:\n{probe.output()[-2000:]}") from None
    except TimeoutError:
        seen = "\n".join(map(json.dumps, results(probe, start)[-5:]))
        raise AssertionError(f"no result {what} within {timeout:g} s; last:\n{seen}") from None


def healthy(r: dict[str, Any]) -> bool:
    return r.get("reported") == ["cam1"] and r["complete"] and not r["errors"] and r["detections"] == 2


@pytest.mark.netns
async def test_links_cut_and_restored_recover_without_restarts(
    network: Network, recorded: dict[str, RecordedCamera]
) -> None:
    rec = recorded["cam1"]
    server = network.process(
        "srv", "server", "drvs-server", "--listen", f"{HOSTS['srv']}:0", "--lease-ttl", str(LEASE_S),
        "--forward-timeout", "1", "--trust-network",
    )  # fmt: skip
    procs = [server]
    try:
        await server.start()
        address = (await server.wait_for_line(SERVER_READY, timeout=30)).group(1)
        assert address.startswith(HOSTS["srv"])
        camera = network.process(
            "cam", "cam1", "drvs-camera", "--id", "cam1", "--source", str(rec.video), "--homography",
            str(rec.homography_file), "--server", address, "--listen", f"{HOSTS['cam']}:0",
            "--max-range", MAX_RANGE, "--heartbeat", "0.5",
        )  # fmt: skip
        procs.append(camera)
        await camera.start()
        await camera.wait_for_line(CAMERA_REGISTERED.format(id="cam1"), timeout=30)
        await server.wait_for_line(rf"camera cam1 registered at {HOSTS['cam']}:", timeout=5)
        probe = network.process(
            "rob", "robot", "fault_roles", "probe-robot", "--server", address, "--listen", f"{HOSTS['rob']}:0",
            "--region=" + ",".join(map(str, CAM1_REGION)), "--period", "0.25", "--timeout", "1",
        )  # fmt: skip
        procs.append(probe)
        await probe.start()
        await probe.wait_for_line(rf"^READY {HOSTS['rob']}:\d+", timeout=30)
        await wait_result(probe, healthy, 10, "with cam1's report")
        pids = [p.pid for p in procs]

        # 1. The camera's cable is cut: it leaves routing when its lease runs out, and requests go
        #    around it (to no camera) instead of failing, saying cam1 did not look.
        await network.cut("cam")
        await server.wait_for_line(r"camera cam1 left routing: lease expired", timeout=LEASE_S + 3)
        await camera.wait_for_line(rf"camera cam1: server {address} unreachable", timeout=5)
        await wait_result(
            probe,
            lambda r: r.get("cameras") == [] and r["missing"] == ["cam1"] and not r["complete"],
            5,
            "routed around cam1, naming it missing",
        )
        #    Plugged back in: the camera finds it was forgotten, registers again by itself, and reports.
        await network.restore("cam")
        await camera.wait_for_line(r"camera cam1 re-registered", timeout=15)
        await wait_result(probe, healthy, 10, "with cam1's report after the camera's link came back")

        # 2. The robot's cable is cut: its requests fail (no reply in time), each within its timeout.
        await network.cut("rob")
        failed = await wait_result(probe, lambda r: "failed" in r, 10, "failing while the robot is cut off")
        assert failed["failed"] in ("DeadlineExceeded", "Unavailable") and failed["seconds"] < 2.5, failed
        await network.restore("rob")
        await wait_result(probe, healthy, 15, "with cam1's report after the robot's link came back")

        # 3. Only the camera -> robot path is cut (a blackhole route on the camera's host): requests
        #    still route, the camera cannot deliver, and the robot's request ends incomplete.
        await ip("-n", network.ns("cam"), "route", "add", "blackhole", f"{HOSTS['rob']}/32")
        await wait_result(
            probe, lambda r: r.get("cameras") == ["cam1"] and not r["complete"], 10, "missing cam1's report"
        )
        await ip("-n", network.ns("cam"), "route", "del", "blackhole", f"{HOSTS['rob']}/32")
        await wait_result(probe, healthy, 15, "with cam1's report after the route came back")

        assert [p.pid for p in procs] == pids and all(p.returncode is None for p in procs), "a process restarted"
    finally:
        for proc in reversed(procs):
            await proc.stop()
