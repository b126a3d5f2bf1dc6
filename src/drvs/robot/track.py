"""Track: the snapshots of one fused continuous request (DrvsClient.track), as the robot's request
stream hands them over, resumed through another server where the client knows several; Tracking,
what track returns."""

from __future__ import annotations

import asyncio
import collections
import logging
import warnings
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING

from shapely.geometry import Polygon

from drvs.core.backoff import Backoff
from drvs.core.errors import DeadlineExceeded, DrvsError, ResourceExhausted, Unavailable
from drvs.core.model import CameraError, DetectionRequest, Snapshot
from drvs.robot.handles import _Delivery, _Sending
from drvs.robot.limits import DEFAULT_RPC_TIMEOUT_S
from drvs.v1 import detection_pb2
from drvs.wire.convert import polygon_from_pb, snapshot_from_pb
from drvs.wire.request_stream import RequestStream

if TYPE_CHECKING:
    from drvs.robot.connection import ClientConnection

log = logging.getLogger("drvs.robot")


class Track(_Delivery):
    """The snapshots of one fused continuous request (DrvsClient.track), as an async iterator that
    ends after the final snapshot (`snapshot.final`).

    The server fuses what every camera reports into world objects (`drvs.core.model.WorldObject`: one
    per physical object, with a track id that stays the same from snapshot to snapshot) and sends
    one `drvs.core.model.Snapshot` per period on the robot's own request stream: no listener is needed.

    Unread snapshots never hold anything back: the stream's reader hands each one over without
    waiting. The newest `max_queued` are kept and older ones dropped and counted in `dropped`; the
    final snapshot is always kept. Leaving `async with` (or breaking out of `async for`) closes the
    track, and the server stops it and its cameras.

    Errors come out of the iteration: Unavailable when the request stream ends before the final
    snapshot (the server restarted, the network broke; the track is over: call track() again for a
    new one) and the client knows one server by its address; a client given several (servers
    sharing one registry), or a DNS name, sends the track again through the next that answers, for
    what remains of it, and the iteration goes on (`resumes`, `gaps_s`; track ids start anew). DeadlineExceeded when no
    final snapshot came within `duration_s` plus the fusion deadline plus `timeout_s` seconds of
    the server's reply.

    - `request_id`: the request; `camera_ids`: the cameras the server dispatched it to;
    - `camera_errors`: camera id -> CameraError for the cameras that see the region but were not
      asked (the server's reply; each snapshot names the cameras missing from it too), as on
      DetectionResult; `missing_cameras` (the same CameraErrors as a tuple) is deprecated;
    - `uncovered`: parts of the region (shapely Polygons, metres) that no camera asked sees (each
      snapshot carries them too, `Snapshot.uncovered`);
    - `received`: snapshots that arrived; `dropped`: those dropped unread; `last`: the newest read;
    - `resumes`: times it was sent again through another server; `gaps_s`: for each, the seconds
      the robot went without a snapshot (the last before the stream ended to the first after).
    """

    def __init__(
        self,
        client: ClientConnection,
        request: DetectionRequest,
        timeout_s: float,
        max_queued: int,
        message: detection_pb2.DetectionRequest | None = None,
        rpc_timeout_s: float = DEFAULT_RPC_TIMEOUT_S,
    ) -> None:
        self._client = client
        self.request = request
        self.request_id = request.request_id
        #: The request as first sent, whole (a resumed track sends it again, for what remains).
        self._message = message
        self._rpc_timeout_s = rpc_timeout_s
        #: Times the track was resumed through another server, and each gap the robot saw: seconds
        #: from the last snapshot before the stream ended to the first after it.
        self.resumes = 0
        self.gaps_s: list[float] = []
        self._broke_at: float | None = None
        self._last_snapshot_at: float | None = None
        self._ends_at = 0.0
        self._resuming: asyncio.Task[None] | None = None
        #: The error that ended the stream a resumed request was sent on, while `_resume` waits.
        self._resume_broke: DrvsError | None = None
        self.camera_ids: tuple[str, ...] = ()
        #: camera id -> why the server did not ask it (it sees the region).
        self.camera_errors: dict[str, CameraError] = {}
        self.uncovered: list[Polygon] = []
        self.received = 0
        self.dropped = 0
        self.last: Snapshot | None = None
        self.closed = False
        #: The final snapshot has arrived (it may still be unread).
        self.finished = False
        self._timeout_s = timeout_s
        self._max_queued = max_queued
        self._pending: collections.deque[Snapshot] = collections.deque()
        self._wakeup: asyncio.Future[None] | None = None
        self._failure: DrvsError | None = None
        self._timer: asyncio.TimerHandle | None = None

    @property
    def missing_cameras(self) -> tuple[CameraError, ...]:
        """Deprecated (removed next release, when `missing_cameras` becomes the camera ids as on
        DetectionResult): the CameraErrors of `camera_errors`, as a tuple."""
        warnings.warn(
            "Track.missing_cameras is deprecated: use Track.camera_errors (camera id -> CameraError)",
            DeprecationWarning,
            2,
        )
        return tuple(self.camera_errors.values())

    def fail(self, error: DrvsError) -> None:
        """End the iteration with `error` (raised once the snapshots already queued are read),
        unless it has already failed: the first failure is the one robot code sees."""
        if self._failure is None:
            self._failure = error
        self._wake()

    async def _attempt(
        self, requests: RequestStream, message: detection_pb2.DetectionRequest
    ) -> detection_pb2.DetectionReply:
        """Send the request once; a stream that ended under an earlier attempt was that attempt's failure."""
        self._failure = None
        return await requests.request(message, self._rpc_timeout_s, self._take)

    def _abandon(self) -> None:
        """Refused or never taken: close it, with nothing to stop at the server."""
        self.finished = True
        self.close()

    def _dispatched(self, reply: detection_pb2.DetectionReply) -> None:
        self.camera_ids = tuple(reply.camera_ids)
        self.camera_errors = {m.camera_id: CameraError(m.code, m.message, m.camera_id) for m in reply.missing_cameras}
        self.uncovered = [polygon_from_pb(p, "uncovered") for p in reply.uncovered]
        request = self.request
        assert request.fusion is not None
        # The final snapshot is due at the end of the duration, the server's grace for late
        # reports (its deadline, or one period) after it at most.
        grace = request.fusion.deadline_s or 1.0 / request.continuous.rate_hz
        if not self._ends_at:
            self._ends_at = asyncio.get_running_loop().time() + request.continuous.duration_s
        remaining = max(0.0, self._ends_at - asyncio.get_running_loop().time())
        limit = remaining + grace + self._timeout_s
        if self._timer is not None:
            self._timer.cancel()
        if not self.finished and not self.closed:
            self._timer = asyncio.get_running_loop().call_later(limit, self._expire, limit)

    def _expire(self, limit: float) -> None:
        self._timer = None
        if not self.finished:
            self.fail(
                DeadlineExceeded(
                    f"request {self.request_id}: no final snapshot within {limit:g} s of the server's reply"
                )
            )

    def _take(self, item: detection_pb2.DetectionReply | DrvsError) -> None:
        """The request stream's reader hands over a reply with a snapshot, or the error that ended
        the stream. Never waits."""
        if self.closed or self.finished:
            return
        if isinstance(item, DrvsError):
            if self._resuming is not None:
                # The stream the resumed request went on ended too (it may have gone to the dead
                # server before the channel knew): `_resume` sends it again.
                self._resume_broke = item
                return
            if self._client.fails_over and self._message is not None:
                # Several servers share the registry: ask another for what remains of the track.
                self._broke_at = self._last_snapshot_at or asyncio.get_running_loop().time()
                self._resuming = asyncio.get_running_loop().create_task(self._resume(item))
                return
            self.fail(
                Unavailable(f"request {self.request_id}: the request stream ended before the final snapshot ({item})")
            )
            return
        now = asyncio.get_running_loop().time()
        if self._broke_at is not None:
            self.gaps_s.append(now - self._broke_at)
            self._broke_at = None
        self._last_snapshot_at = now
        snapshot = snapshot_from_pb(item.snapshot, self.request_id, self.uncovered)
        self.received += 1
        if snapshot.final:
            self.finished = True
            self._client._release(self.request_id)
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
        elif len(self._pending) >= self._max_queued:
            self._pending.popleft()  # never the final one: nothing comes after it
            self.dropped += 1
        self._pending.append(snapshot)
        self._wake()

    async def _resume(self, why: DrvsError) -> None:
        """Send the track again, through the client's channel (which moves on to a server that
        answers), for what remains of its duration; the robot's iteration goes on. Track ids start
        anew (another server's tracker). A server that is down, or refuses it for load (with a retry
        hint), is asked again after a backoff. Gives up, as a single-server track does (Unavailable),
        when less than a period remains, no server takes it before the track would have ended, or a
        server refuses it for good."""
        assert self._message is not None
        loop = asyncio.get_running_loop()
        period = 1.0 / self.request.continuous.rate_hz
        backoff = Backoff(0.05, 1.0)
        try:
            while not (self.closed or self.finished):
                remaining = self._ends_at - loop.time()
                if remaining < period:
                    raise Unavailable(f"request {self.request_id}: no server took it back before it would have ended")
                message = detection_pb2.DetectionRequest()
                message.CopyFrom(self._message)
                message.continuous.duration_s = remaining
                requests = self._client._requests
                assert requests is not None
                self._resume_broke = None
                try:
                    reply = await requests.request(message, self._rpc_timeout_s, self._take)
                    if self._resume_broke is not None:  # answered, then its stream ended
                        raise Unavailable(str(self._resume_broke))
                except (Unavailable, ResourceExhausted) as exc:
                    hint = exc.retry_after_s if isinstance(exc, ResourceExhausted) else 0.0
                    if isinstance(exc, ResourceExhausted) and not hint:
                        raise  # the robot's own budget (no hint), not the server's load: final
                    # Down, or refused for load (the survivors take the dead server's robots): again
                    # after the backoff, and no sooner than the refusal asked.
                    wait = max(backoff.next(), hint)
                    log.info("request %s: no server takes it yet (%s); again in %.2f s", self.request_id, exc, wait)
                    await asyncio.sleep(wait)
                    continue
                self.resumes += 1
                log.info(
                    "request %s: resumed through another server for the remaining %.1f s (%s)",
                    self.request_id,
                    remaining,
                    why,
                )
                self._dispatched(reply)
                return
        except DrvsError as exc:
            self.fail(
                Unavailable(
                    f"request {self.request_id}: the request stream ended before the final snapshot ({why}); "
                    f"resuming failed: {exc}"
                )
            )
        finally:
            self._resuming = None

    def __aiter__(self) -> AsyncIterator[Snapshot]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[Snapshot]:
        try:
            while True:
                if self._pending:
                    snapshot = self._pending.popleft()
                    self.last = snapshot
                    yield snapshot
                    if snapshot.final:
                        return
                    continue
                if self._failure is not None:
                    raise self._failure
                if self.closed or self.finished:
                    return
                self._wakeup = asyncio.get_running_loop().create_future()
                await self._wakeup
        finally:
            self.close()

    def close(self) -> None:
        """Stop the track: the server is told to stop it (and its cameras) unless it is over."""
        if self.closed:
            return
        self.closed = True
        if self._resuming is not None:
            self._resuming.cancel()
        self._client._release(self.request_id)
        if not self.finished and not isinstance(self._failure, Unavailable):
            self._client._cancel_at_server(self.request_id)
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._wake()
        self._client._forget(self.request_id)


class Tracking(_Sending[Track]):
    """What DrvsClient.track returns. Three ways to use it:

        async for snapshot in drvs.track(YELLOW, region, rate_hz=10, duration_s=5):
            ...                                 # sent on the first iteration; break stops it
        async with drvs.track(...) as track:    # sent on entering; leaving stops it
            async for snapshot in track: ...
        track = await drvs.track(...)           # sent now; call track.close() when done

    The request is sent when it is iterated, entered or awaited, not before; a server that refuses
    it raises the DrvsError it stands for then (InvalidArgument, ResourceExhausted ...), and one
    that cannot be reached Unavailable, after the attempts `retry` allows.
    """

    def __aiter__(self) -> AsyncIterator[Snapshot]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[Snapshot]:
        track = self._opened if self._opened is not None else await self._opening()
        try:
            async for snapshot in track:
                yield snapshot
        finally:
            track.close()


async def open_track(
    client: ClientConnection,
    request: DetectionRequest,
    message: detection_pb2.DetectionRequest,
    timeout_s: float,
    rpc_timeout_s: float,
    max_queued: int,
) -> Track:
    """Send a fused continuous request (DrvsClient.track): its Track, once the server replied."""
    whole = detection_pb2.DetectionRequest()
    whole.CopyFrom(message)  # the request stream leaves out what repeats: keep it whole to resend
    track = Track(client, request, timeout_s, max_queued, whole, rpc_timeout_s)
    client._register(track)
    requests = client._requests
    assert requests is not None
    try:
        reply = await client._asking(f"request {message.request_id}", lambda: track._attempt(requests, message))
    except DeadlineExceeded:
        track.close()  # the server may have taken it: tell it to stop
        raise
    except BaseException:
        track._abandon()  # refused or never taken: nothing to stop at the server
        raise
    track._dispatched(reply)
    return track
