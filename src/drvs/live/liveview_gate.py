"""A token in front of a live view (`drvs-server --foxglove-token`): foxglove-sdk's WebSocket server
checks no credential, so with a token the SDK listens on 127.0.0.1 at a port of its own and this
gate listens where the view was asked to, lets a WebSocket through only when it presents the token,
and relays its frames both ways unchanged.

The token is presented as `?token=TOKEN` in the URL (what the Foxglove app can send: open
`ws://HOST:PORT/?token=TOKEN`) or as `Authorization: Bearer TOKEN`; anything else is answered 401
before any of the view's data flows. The gate runs on an event loop of its own, in its own thread,
so the server's requests never wait for it.

What it does not cover: the SDK's own port on 127.0.0.1, which anyone with a shell on the host can
reach (loopback is trusted, as without a token); and it is plain `ws://` (no TLS): keep the token
off networks others can read, or put a TLS proxy in front."""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import threading
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

log = logging.getLogger("drvs.live.liveview")

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
#: Connections the gate relays at once; more are refused (503) before the token is even read.
MAX_CONNECTIONS = 64


def presented(path: str, headers: Any) -> str:
    """The token a WebSocket handshake presents ("" none): `?token=` first, else a Bearer header."""
    query = parse_qs(urlsplit(path).query).get("token")
    if query:
        return query[0]
    auth = headers.get("Authorization", "") or ""
    return auth[7:].strip() if auth.lower().startswith("bearer ") else ""


class TokenGate:
    """Listens on (host, port) (0: a free one, then `.port`) and relays WebSockets that present
    `token` to the view at ws://127.0.0.1:`inner_port`. `close()` stops it and every relay."""

    def __init__(self, host: str, port: int, inner_port: int, token: str) -> None:
        self.host = host
        self.inner_port = inner_port
        self._token = token.encode()
        self._loop = asyncio.new_event_loop()
        self._server: Any = None
        self._connections = 0
        self.refused = 0
        started: list[BaseException | int] = []
        ready = threading.Event()

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(self._serve(host, port))
                started.append(self._server.sockets[0].getsockname()[1])
            except BaseException as exc:  # e.g. the port is taken: said by the constructor
                started.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_until_complete(self._server.wait_closed())

        self._thread = threading.Thread(target=run, name="drvs-liveview-gate", daemon=True)
        self._thread.start()
        ready.wait()
        if isinstance(started[0], BaseException):
            self._loop.close()
            raise started[0]
        self.port = started[0]

    async def _serve(self, host: str, port: int) -> Any:
        from websockets.asyncio.server import serve
        from websockets.typing import Subprotocol

        return await serve(
            self._relay,
            host,
            port,
            process_request=self._check,
            subprotocols=[Subprotocol(p) for p in SUBPROTOCOLS],
            max_size=None,
            compression=None,
        )

    def _check(self, connection: Any, request: Any) -> Any:
        if self._connections >= MAX_CONNECTIONS:
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "too many live view connections\n")
        if not hmac.compare_digest(presented(request.path, request.headers).encode(), self._token):
            self.refused += 1
            log.warning("live view: a connection from %s without its token refused", connection.remote_address)
            return connection.respond(HTTPStatus.UNAUTHORIZED, "this live view needs its token: ?token=...\n")
        return None

    async def _relay(self, outer: Any) -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed
        from websockets.typing import Subprotocol

        self._connections += 1
        try:
            async with connect(
                f"ws://127.0.0.1:{self.inner_port}",
                subprotocols=[Subprotocol(outer.subprotocol or SUBPROTOCOLS[0])],
                max_size=None,
                compression=None,
            ) as inner:

                async def pump(source: Any, sink: Any) -> None:
                    with contextlib.suppress(ConnectionClosed):
                        async for frame in source:
                            await sink.send(frame)

                both = [asyncio.create_task(pump(outer, inner)), asyncio.create_task(pump(inner, outer))]
                await asyncio.wait(both, return_when=asyncio.FIRST_COMPLETED)
                for task in both:
                    task.cancel()
                await asyncio.gather(*both, return_exceptions=True)
        except (OSError, ConnectionClosed) as exc:
            log.warning("live view: relaying to the view failed: %s", exc)
        finally:
            self._connections -= 1

    def close(self) -> None:
        if self._server is None or self._loop.is_closed():
            return

        def stop() -> None:
            self._server.close(close_connections=True)

        self._loop.call_soon_threadsafe(stop)
        self._thread.join(10)
        with contextlib.suppress(Exception):
            self._loop.close()
