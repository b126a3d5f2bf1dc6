"""A TCP relay that counts the bytes it carries: real socket bytes, not message sizes."""

from __future__ import annotations

import asyncio
import contextlib

_CHUNK = 65536


class CountingRelay:
    """Accepts connections on a local port and forwards each to `target`, counting both directions.

    The target may be set after start() (set_target); connections wait for it. With bucket_s, the
    bytes carried (both directions) are also kept per interval since start, for plots.
    """

    def __init__(
        self,
        target_host: str | None = None,
        target_port: int = 0,
        listen_host: str = "127.0.0.1",
        bucket_s: float = 0.0,
    ) -> None:
        self.target: tuple[str, int] | None = None
        self._target_known = asyncio.Event()
        if target_host is not None:
            self.set_target(target_host, target_port)
        self.listen_host = listen_host
        self.port = 0
        self.to_target = 0
        self.from_target = 0
        self.bucket_s = bucket_s
        self.timeline: dict[int, int] = {}
        self._t0 = 0.0
        self._server: asyncio.Server | None = None
        self._pipes: set[asyncio.Task[None]] = set()

    def set_target(self, host: str, port: int) -> None:
        self.target = (host, port)
        self._target_known.set()

    @property
    def total(self) -> int:
        return self.to_target + self.from_target

    async def start(self) -> int:
        self._t0 = asyncio.get_running_loop().time()
        self._server = await asyncio.start_server(self._accept, self.listen_host, 0)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            for task in list(self._pipes):
                task.cancel()
            await asyncio.gather(*self._pipes, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None

    async def _accept(self, client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        try:
            await self._target_known.wait()
            assert self.target is not None
            target_r, target_w = await asyncio.open_connection(*self.target)
        except OSError:
            client_w.close()
            return
        up = asyncio.get_running_loop().create_task(self._pipe(client_r, target_w, True))
        down = asyncio.get_running_loop().create_task(self._pipe(target_r, client_w, False))
        for task in (up, down):
            self._pipes.add(task)
            task.add_done_callback(self._pipes.discard)
        await asyncio.gather(up, down, return_exceptions=True)

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, upstream: bool) -> None:
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
            with contextlib.suppress(Exception):
                writer.close()
