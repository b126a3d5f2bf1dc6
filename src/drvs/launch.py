"""Start DRVS roles as separate processes and wait for what they log: used by the demo and the tests."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TextIO, TypeVar

T = TypeVar("T")

#: Longest output line read (a benchmark's result line can be large); a longer one is dropped.
MAX_LINE_BYTES = 16 * 1024 * 1024
SERVER_READY = re.compile(r"drvs-server listening on (\S+)")
CAMERA_REGISTERED = r"camera {id} (?:re-)?registered with"


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
        return self

    async def _read(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        while True:
            try:
                raw = await self.process.stdout.readline()
            except ValueError:  # longer than MAX_LINE_BYTES: asyncio has dropped it
                raw = b"<drvs.launch: an output line longer than MAX_LINE_BYTES was dropped>\n"
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
                        raise RuntimeError(
                            f"{self.name} exited (code {self.returncode}) before {what}:\n"
                            + "\n".join(self.lines[-20:])
                        )
                    await self._changed.wait()

        try:
            return await asyncio.wait_for(wait(), timeout)
        except asyncio.TimeoutError:
            raise TimeoutError(
                f"{self.name}: still no {what} after {timeout:g} s:\n" + "\n".join(self.lines[-20:])
            ) from None

    def output(self) -> str:
        return "\n".join(self.lines)

    def kill(self) -> None:
        """SIGKILL: simulate a crash."""
        if self.process is not None and self.process.returncode is None:
            self.process.kill()

    async def wait(self, timeout: float = 10.0) -> int:
        assert self.process is not None
        code = await asyncio.wait_for(self.process.wait(), timeout)
        if self._reader is not None:
            await self._reader
        return code

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


async def start_server(
    *args: str, echo: TextIO | None = None, env: dict[str, str] | None = None
) -> tuple[ManagedProcess, str]:
    proc = await ManagedProcess.entry_point(
        "server", "drvs-server", "--listen", "127.0.0.1:0", *args, echo=echo, env=env
    ).start()
    m = await proc.wait_for_line(SERVER_READY)
    return proc, m.group(1)


async def start_camera(
    camera_id: str,
    source: str | Path,
    homography: str | Path,
    server: str,
    *args: str,
    echo: TextIO | None = None,
    env: dict[str, str] | None = None,
) -> ManagedProcess:
    proc = ManagedProcess.entry_point(
        camera_id,
        "drvs-camera",
        "--id",
        camera_id,
        "--source",
        str(source),
        "--homography",
        str(homography),
        "--server",
        server,
        "--listen",
        "127.0.0.1:0",
        *args,
        echo=echo,
        env=env,
    )
    await proc.start()
    await proc.wait_for_line(CAMERA_REGISTERED.format(id=re.escape(camera_id)))
    return proc
