"""Start DRVS roles as separate processes and wait until they are ready: used by the demo and the tests.

Readiness: a role prints its address once ("drvs-server listening on ADDR", "camera ID listening on
ADDR"); then its gRPC health service must answer SERVING. Registration with the server has no health
service of its own, so `start_camera` also waits for the camera's "registered with" line.
Every helper here stops and reaps the process it started when it fails or times out.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import re
import shutil
import signal
import socket
import sys
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, TextIO, TypeVar

from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc

from drvs.core.net import format_address, parse_address
from drvs.wire._cli import add_security_arguments, security_from

T = TypeVar("T")

#: Longest output line read (a benchmark's result line can be large); a longer one is dropped.
MAX_LINE_BYTES = 16 * 1024 * 1024
SERVER_READY = re.compile(r"drvs-server listening on (\S+)")
#: What a drvs-server with --foxglove logs before SERVER_READY: where its live view listens.
LIVE_READY = re.compile(r"live view on (wss?://\S+)")
#: A camera's own listener (format with id=re.escape(camera_id)); group 1 is the address.
CAMERA_LISTENING = r"camera {id} listening on (\S+)"
CAMERA_REGISTERED = r"camera {id} (?:re-)?registered with"
#: How long the start helpers wait for each step (address, health, registration) by default.
READY_TIMEOUT_S = 30.0


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process (all its threads) so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def running() -> set[ManagedProcess]:
    """Every ManagedProcess started and not yet seen to exit (a test harness kills what a failed
    test left behind: see `kill`)."""
    _STARTED.difference_update([p for p in _STARTED if p.returncode is not None])
    return set(_STARTED)


_STARTED: set[ManagedProcess] = set()


class ManagedProcess:
    """A child process whose combined output is read line by line, so callers can await a log line."""

    def __init__(
        self, name: str, argv: Sequence[str], *, env: dict[str, str] | None = None, echo: TextIO | None = None
    ) -> None:
        self.name = name
        self.argv = list(argv)
        self.env = env
        self.echo = echo
        self.lines: list[str] = []
        self.process: asyncio.subprocess.Process | None = None
        self._changed = asyncio.Condition()
        self._reader: asyncio.Task[None] | None = None
        self._eof = False

    @classmethod
    def entry_point(cls, name: str, command: str, *args: str, **kwargs: object) -> ManagedProcess:
        """Run one of this package's console scripts: the installed script beside the interpreter, or
        the same entry point through `python -c` when the package is not installed as scripts."""
        script = Path(sys.executable).parent / command
        if script.exists():
            return cls(name, [str(script), *args], **kwargs)  # type: ignore[arg-type]
        module = {
            "drvs-server": "drvs.server.cli",
            "drvs-camera": "drvs.camera.cli",
            "drvs-robot": "drvs.robot.cli",
            "drvs-sim": "drvs.sim.cli",
            "drvs-office": "drvs.sim.office",
            "drvs-bench": "drvs_bench.cli",
        }[command]
        code = f"import sys; from {module} import main; sys.exit(main())"
        return cls(name, [sys.executable, "-c", code, *args], **kwargs)  # type: ignore[arg-type]

    @property
    def pid(self) -> int:
        assert self.process is not None
        return self.process.pid

    @property
    def returncode(self) -> int | None:
        return None if self.process is None else self.process.returncode

    async def __aenter__(self) -> ManagedProcess:
        """`async with ManagedProcess(...) as proc:` starts it, and stops and reaps it on the way out."""
        return await self.start()

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    async def start(self) -> ManagedProcess:
        env = dict(os.environ if self.env is None else self.env)
        env.setdefault("PYTHONUNBUFFERED", "1")
        self.process = await asyncio.create_subprocess_exec(
            *self.argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
            env=env,
            limit=MAX_LINE_BYTES,
        )
        self._reader = asyncio.get_running_loop().create_task(self._read())
        _STARTED.add(self)
        return self

    async def _read(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        while True:
            try:
                raw = await self.process.stdout.readline()
            except ValueError:  # longer than MAX_LINE_BYTES: asyncio has dropped it
                raw = b"<drvs.tools.launch: an output line longer than MAX_LINE_BYTES was dropped>\n"
            async with self._changed:
                if not raw:
                    self._eof = True
                    self._changed.notify_all()
                    return
                line = raw.decode(errors="replace").rstrip("\n")
                self.lines.append(line)
                if self.echo is not None:
                    print(f"[{self.name}] {line}", file=self.echo, flush=True)
                self._changed.notify_all()

    async def wait_for_lines(
        self, pattern: str | re.Pattern[str], count: int, timeout: float = 30.0, start: int = 0
    ) -> list[re.Match[str]]:
        """The first `count` lines (from index `start`) matching `pattern`, once there are that many
        (the N workers of `drvs-server --workers N` each log their start)."""
        regex = re.compile(pattern) if isinstance(pattern, str) else pattern
        found: list[re.Match[str]] = []

        def check(line: str) -> list[re.Match[str]] | None:
            match = regex.search(line)
            if match is not None:
                found.append(match)
            return found if len(found) >= count else None

        return await self.wait_for(check, f"{count} lines logging {regex.pattern!r}", timeout, start)

    async def wait_for_line(
        self, pattern: str | re.Pattern[str], timeout: float = 30.0, start: int = 0
    ) -> re.Match[str]:
        """The first line (from index `start`) matching `pattern`; raises if the process ends first."""
        regex = re.compile(pattern) if isinstance(pattern, str) else pattern
        return await self.wait_for(regex.search, f"logging {regex.pattern!r}", timeout, start)

    async def wait_for(self, check: Callable[[str], T | None], what: str, timeout: float = 30.0, start: int = 0) -> T:
        """The first non-None `check(line)` over the lines from index `start`, as they arrive;
        raises, naming `what` ("logging 'READY'"), if the process ends first or `timeout` passes."""
        seen = start

        def find() -> T | None:
            nonlocal seen
            while seen < len(self.lines):
                found = check(self.lines[seen])
                seen += 1
                if found is not None:
                    return found
            return None

        async def wait() -> T:
            async with self._changed:
                while True:
                    found = find()
                    if found is not None:
                        return found
                    if self._eof:
                        break
                    await self._changed.wait()
            # Its output has ended: it is exiting. Its exit code makes the error clearer.
            if self.process is not None:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(asyncio.shield(self.process.wait()), 5)
            raise self.exited_before(what)

        try:
            return await asyncio.wait_for(wait(), timeout)
        except asyncio.TimeoutError:
            raise TimeoutError(f"{self.name}: still no {what} after {timeout:g} s:\n{self.tail()}") from None

    def output(self) -> str:
        return "\n".join(self.lines)

    def tail(self) -> str:
        """Its last 20 lines, for an error message."""
        return "\n".join(self.lines[-20:])

    def exited_before(self, what: str) -> RuntimeError:
        """The error for a process that exited before `what` ("logging 'READY'")."""
        return RuntimeError(f"{self.name} exited (code {self.returncode}) before {what}:\n{self.tail()}")

    def kill(self) -> None:
        """SIGKILL: simulate a crash. Safe without a running event loop (the child is reaped anyway)."""
        if self.process is not None and self.process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.process.pid, signal.SIGKILL)

    async def wait(self, timeout: float = 10.0) -> int:
        """Its exit code once it exits by itself. If it has not within `timeout` (or the wait is
        cancelled), it is killed and reaped, and TimeoutError (or the cancellation) is raised."""
        assert self.process is not None
        try:
            code = await asyncio.wait_for(self.process.wait(), timeout)
        except BaseException as exc:
            self.kill()
            await asyncio.shield(self._reap())
            if isinstance(exc, asyncio.TimeoutError):
                raise TimeoutError(f"{self.name} did not exit within {timeout:g} s (killed):\n{self.tail()}") from None
            raise
        if self._reader is not None:
            await self._reader
        return code

    async def _reap(self) -> None:
        assert self.process is not None
        await self.process.wait()
        if self._reader is not None:
            await self._reader

    async def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM and wait; SIGKILL only if it does not stop in time. Always reaps."""
        if self.process is None:
            return None
        if self.process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                self.process.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(self.process.wait(), timeout)
            except asyncio.TimeoutError:
                self.kill()
                await self.process.wait()
        if self._reader is not None:
            await self._reader
        return self.process.returncode


def _loopback_if_wildcard(address: str) -> str:
    """A listener bound to every interface (0.0.0.0, ::) is probed on this host's loopback."""
    host, port = parse_address(address, allow_port_zero=True)
    wildcard = {"0.0.0.0": "127.0.0.1", "::": "::1"}
    return format_address(wildcard[host], port) if host in wildcard else address


def _probe_security_args(args: Sequence[str]) -> dict[str, object]:
    """The security flags among a role's arguments (the rest ignored)."""
    p = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    add_security_arguments(p, "")
    known, _ = p.parse_known_args(list(args))
    return vars(known)


async def wait_serving(
    address: str,
    proc: ManagedProcess | None = None,
    *,
    args: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
    timeout: float = READY_TIMEOUT_S,
) -> None:
    """Until the gRPC health service at `address` answers SERVING (for the whole server, service "").
    `args`/`env`: the role's own command line and environment, for its TLS files (the probe dials it
    as the role itself would be dialled; health needs no token). Raises, with the process's last
    lines, if `proc` exits first or `timeout` passes."""
    security = security_from(_probe_security_args(args), os.environ if env is None else env)
    dial = _loopback_if_wildcard(address)

    async def serving() -> None:
        async with security.channel(dial) as channel:
            stub = health_pb2_grpc.HealthStub(channel)
            request = health_pb2.HealthCheckRequest(service="")
            # Watch sends the current status, then every change: no polling.
            async for reply in stub.Watch(request, timeout=timeout, wait_for_ready=True):
                if reply.status == health_pb2.HealthCheckResponse.SERVING:
                    return
            raise RuntimeError(f"{address}: the health watch ended before SERVING")

    what = f"gRPC health SERVING at {address}"
    name = proc.name if proc is not None else address
    try:
        await _unless_exited(proc, serving(), what, timeout, name)
    except aio.AioRpcError as exc:  # its deadline: the same timeout
        tail = "" if proc is None else ":\n" + proc.tail()
        raise TimeoutError(f"{name}: still no {what} after {timeout:g} s ({exc.code().name}){tail}") from None


async def _unless_exited(
    proc: ManagedProcess | None, awaitable: Awaitable[T], what: str, timeout: float, name: str = "wait"
) -> T:
    """`awaitable`'s result, unless `proc` exits first (RuntimeError) or `timeout` passes (TimeoutError)."""
    task = asyncio.ensure_future(awaitable)
    waits: set[asyncio.Future[Any]] = {task}
    exited: asyncio.Future[int] | None = None
    if proc is not None and proc.process is not None:
        exited = asyncio.ensure_future(proc.process.wait())
        waits.add(exited)
    try:
        done, _ = await asyncio.wait(waits, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
        if task in done:
            return task.result()
        if exited is not None and exited in done:
            assert proc is not None
            if proc._reader is not None:
                await proc._reader
            raise proc.exited_before(what)
        name = proc.name if proc is not None else name
        tail = "" if proc is None else ":\n" + proc.tail()
        raise TimeoutError(f"{name}: still no {what} after {timeout:g} s{tail}")
    finally:
        for waiting in waits:
            waiting.cancel()
        await asyncio.gather(*waits, return_exceptions=True)


def _deadline(timeout: float) -> Callable[[], float]:
    """Seconds left of `timeout` from now (at least a little, so a last step can still report why)."""
    end = asyncio.get_running_loop().time() + timeout

    def left() -> float:
        return max(0.01, end - asyncio.get_running_loop().time())

    return left


async def start_server(
    *args: str, echo: TextIO | None = None, env: dict[str, str] | None = None, timeout: float = READY_TIMEOUT_S
) -> tuple[ManagedProcess, str]:
    """drvs-server on 127.0.0.1 port 0 (unless `args` say otherwise): (process, address) once its
    health service answers SERVING, all within `timeout` s. On failure or timeout the process is
    stopped and reaped."""
    proc = await ManagedProcess.entry_point(
        "server", "drvs-server", "--listen", "127.0.0.1:0", *args, echo=echo, env=env
    ).start()
    left = _deadline(timeout)
    try:
        address = (await proc.wait_for_line(SERVER_READY, timeout=left())).group(1)
        await wait_serving(address, proc, args=args, env=env, timeout=left())
    except BaseException:
        await asyncio.shield(proc.stop())
        raise
    return proc, address


@contextlib.asynccontextmanager
async def running_server(
    *args: str, echo: TextIO | None = None, env: dict[str, str] | None = None, timeout: float = READY_TIMEOUT_S
) -> AsyncIterator[tuple[ManagedProcess, str]]:
    """`async with running_server(...) as (proc, address):` start_server, stopped and reaped on exit."""
    proc, address = await start_server(*args, echo=echo, env=env, timeout=timeout)
    try:
        yield proc, address
    finally:
        await proc.stop()


async def start_camera(
    camera_id: str,
    source: str | Path,
    homography: str | Path | None,
    server: str,
    *args: str,
    echo: TextIO | None = None,
    env: dict[str, str] | None = None,
    timeout: float = READY_TIMEOUT_S,
) -> ManagedProcess:
    """drvs-camera listening on 127.0.0.1 port 0, returned once its health service answers SERVING
    and it has registered with `server`, all within `timeout` s. On failure or timeout it is
    stopped and reaped. `homography` None: a mobile camera, its --mount and --pose-source in `args`."""
    proc = ManagedProcess.entry_point(
        camera_id,
        "drvs-camera",
        "--id",
        camera_id,
        "--source",
        str(source),
        *(("--homography", str(homography)) if homography is not None else ()),
        "--server",
        server,
        "--listen",
        "127.0.0.1:0",
        *args,
        echo=echo,
        env=env,
    )
    await proc.start()
    await camera_ready(proc, camera_id, args=args, env=env, timeout=timeout)
    return proc


async def camera_ready(
    proc: ManagedProcess,
    camera_id: str,
    *,
    args: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
    timeout: float = READY_TIMEOUT_S,
) -> str:
    """A started drvs-camera's own address, once its health service answers SERVING and it has
    registered with its server, all within `timeout` s. `args`/`env`: its command line and
    environment, for its TLS files (a camera configured by --config file must not use TLS here).
    On failure or timeout the process is stopped and reaped."""
    left = _deadline(timeout)
    try:
        listening = await proc.wait_for_line(CAMERA_LISTENING.format(id=re.escape(camera_id)), timeout=left())
        address = listening.group(1)
        await wait_serving(address, proc, args=args, env=env, timeout=left())
        # No health service says "registered": the camera's log line does.
        await proc.wait_for_line(CAMERA_REGISTERED.format(id=re.escape(camera_id)), timeout=left())
    except BaseException:
        await asyncio.shield(proc.stop())
        raise
    return address


# --- etcd ----------------------------------------------------------------------------------------

ETCD = "etcd"  # Debian's etcd-server package (./run installs it)
#: How DRVS runs etcd (docs/operations.md, "Running etcd for DRVS"): history older than this is
#: compacted (etcd's --auto-compaction-mode periodic --auto-compaction-retention), and the store may
#: grow to this many bytes (--quota-backend-bytes) before etcd refuses writes. Every registration
#: and pose update is a revision etcd keeps until compacted; without compaction any steady writer
#: fills any quota.
ETCD_COMPACTION_RETENTION = "5m"
ETCD_QUOTA_BYTES = 256 * 1024 * 1024


def free_ports(count: int) -> list[int]:
    """`count` loopback ports free a moment ago (etcd advertises its ports, so it cannot take 0)."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket()
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


@dataclass
class EtcdMember:
    """One member of a real etcd cluster on loopback: its process, name and ports."""

    name: str
    client_port: int
    peer_port: int
    data_dir: Path
    proc: ManagedProcess | None = None
    #: TLS for clients: (CA, certificate, key) PEM files; clients must present a certificate too.
    tls: tuple[Path, Path, Path] | None = None
    #: History kept before compaction (etcd's duration syntax: "5m", "1h"), and the store's quota.
    compaction_retention: str = ETCD_COMPACTION_RETENTION
    quota_bytes: int = ETCD_QUOTA_BYTES

    @property
    def client_url(self) -> str:
        return f"{'https' if self.tls else 'http'}://127.0.0.1:{self.client_port}"

    @property
    def peer_url(self) -> str:
        return f"http://127.0.0.1:{self.peer_port}"

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.client_port}"

    async def start(self, cluster: str, state: str = "new", echo: TextIO | None = None) -> None:
        """Start (or restart, on its data) this member of `cluster` (NAME=PEER_URL,...)."""
        if shutil.which(ETCD) is None:
            raise FileNotFoundError("etcd: not installed (Debian's etcd-server; ./run setup installs it)")
        self.proc = await ManagedProcess(
            f"etcd-{self.name}",
            [
                ETCD, "--name", self.name, "--data-dir", str(self.data_dir),
                "--listen-client-urls", self.client_url, "--advertise-client-urls", self.client_url,
                "--listen-peer-urls", self.peer_url, "--initial-advertise-peer-urls", self.peer_url,
                "--initial-cluster", cluster, "--initial-cluster-state", state,
                "--initial-cluster-token", "drvs", "--heartbeat-interval", "50", "--election-timeout", "500",
                "--log-level", "warn", "--quota-backend-bytes", str(self.quota_bytes),
                "--auto-compaction-mode", "periodic", "--auto-compaction-retention", self.compaction_retention,
                *(
                    ("--trusted-ca-file", str(self.tls[0]), "--cert-file", str(self.tls[1]),
                     "--key-file", str(self.tls[2]), "--client-cert-auth")
                    if self.tls else ()
                ),
            ],
            echo=echo,
        ).start()  # fmt: skip

    async def stop(self) -> None:
        if self.proc is not None:
            await self.proc.stop()

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()


async def start_etcd(
    data_dir: Path,
    members: int = 1,
    *,
    echo: TextIO | None = None,
    tls: tuple[Path, Path, Path] | None = None,
    client_tls: tuple[Path, Path] | None = None,
    auth_users: Sequence[str] = (),
    compaction_retention: str = ETCD_COMPACTION_RETENTION,
    quota_bytes: int = ETCD_QUOTA_BYTES,
) -> list[EtcdMember]:
    """A real etcd cluster of `members` on loopback ports, its data under `data_dir`, returned once
    it answers; on failure every member is stopped and reaped. `tls`: (CA, certificate, key) for
    its client port, which then asks clients for a certificate: `client_tls` (certificate, key) is
    the one the readiness check presents. `auth_users` (with `tls`): etcd's access control on
    (drvs.server.etcd_auth), only these certificates' common names may use DRVS's keys. Compaction and
    quota as DRVS runs etcd (ETCD_*)."""
    import grpc

    from drvs.server.etcd import Endpoints, wait_ready

    ports = free_ports(2 * members)
    cluster = [
        EtcdMember(
            f"m{i}",
            ports[2 * i],
            ports[2 * i + 1],
            data_dir / f"m{i}",
            tls=tls,
            compaction_retention=compaction_retention,
            quota_bytes=quota_bytes,
        )
        for i in range(members)
    ]
    credentials = None
    if tls is not None:
        assert client_tls is not None, "client_tls: the readiness check needs a client certificate"
        credentials = grpc.ssl_channel_credentials(
            tls[0].read_bytes(), client_tls[1].read_bytes(), client_tls[0].read_bytes()
        )
    initial = ",".join(f"{m.name}={m.peer_url}" for m in cluster)
    try:
        for m in cluster:
            await m.start(initial, echo=echo)
        endpoints = Endpoints(tuple(("127.0.0.1", m.client_port) for m in cluster))
        await wait_ready(endpoints, READY_TIMEOUT_S, credentials=credentials)
        if auth_users:
            from drvs.server import etcd_auth
            from drvs.server.etcd import EtcdClient

            assert credentials is not None, "auth_users: etcd's users are certificates' names: needs tls"
            async with EtcdClient(endpoints, credentials=credentials) as client:
                await etcd_auth.enable(client, auth_users)
    except BaseException:
        for m in cluster:
            await asyncio.shield(m.stop())
        raise
    return cluster


@contextlib.asynccontextmanager
async def running_etcd(
    members: int = 1,
    *,
    tls: tuple[Path, Path, Path] | None = None,
    client_tls: tuple[Path, Path] | None = None,
    auth_users: Sequence[str] = (),
) -> AsyncIterator[list[EtcdMember]]:
    """`async with running_etcd() as members:` start_etcd (TLS, client certificates and access
    control as it takes them) with its data in a temporary folder; every member stopped and
    reaped, and the folder removed, on exit."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="drvs-etcd-") as data:
        cluster = await start_etcd(Path(data), members, tls=tls, client_tls=client_tls, auth_users=auth_users)
        try:
            yield cluster
        finally:
            for m in cluster:
                await m.stop()
