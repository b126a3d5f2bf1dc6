"""A camera registry several DRVS servers share in etcd (`drvs-server --registry etcd://...`).

Each registration is one key, `/drvs/v1/cameras/<camera_id>`, whose value is a `Record` (JSON: what
the camera registered, who holds the id and the registration's secret, the forward secret the
servers present to the camera) attached to an etcd lease whose TTL is the camera's lease. Any
server renews it (a heartbeat keeps the lease alive) or deletes it (deregistration revokes the
lease). A registration replaces a key only by compare-and-put against the value it checked the
id's holder in, so two servers cannot both hand one id to different holders.

Every server watches the prefix from the revision it read it at, and keeps its own index (its
in-memory `Registry`, the STRtree routing reads) current: a put adds or replaces a camera, a delete
(deregistration, or the lease running out with nobody renewing it) removes it. etcd's delete event
cannot tell those two apart, so a deregistration first writes a marker, `/drvs/v1/leaving/<id>`,
naming the lease it ends (on a short lease of its own): a camera's delete with no marker for its
lease before it is a lapse, and every server remembers the camera as lost (missing UNAVAILABLE,
its floor uncovered), as a server with the in-memory registry does. When etcd cannot be
reached, the server routes on the last registry it knew, says so in its log, and refuses
registrations (UNAVAILABLE); when etcd answers again it reads the prefix anew and reconciles.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
import math
import secrets
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from drvs.core.backoff import Backoff
from drvs.core.errors import DrvsError, FailedPrecondition, ResourceExhausted, Unavailable
from drvs.core.model import DEFAULT_FRAME
from drvs.server.claims import Claim
from drvs.server.etcd import Endpoints, EtcdClient, Event
from drvs.wire import metrics

log = logging.getLogger("drvs.server.shared")

ROOT = b"/drvs/v1/"
PREFIX = ROOT + b"cameras/"
#: A mobile camera's latest pose, on the camera's lease (it goes with the camera).
POSES = ROOT + b"poses/"
#: A deregistration's marker, written before its camera's key is deleted; its value the lease ended.
LEAVING = ROOT + b"leaving/"
#: How long a marker stays (its own etcd lease), seconds: a server that reads the registry again
#: after an etcd outage longer than this takes a camera deregistered meanwhile for one that lapsed.
LEAVING_TTL_S = 300.0
#: Reconnect backoff when etcd cannot be reached, seconds: first wait and the most.
INITIAL_BACKOFF_S = 0.2
MAX_BACKOFF_S = 5.0
#: Registrations one identity may make a minute, and pose updates it may send a second, on a registry
#: shared in etcd (--registration-rate, --pose-write-rate): each is a write etcd keeps until it is
#: compacted (about 800 B a registration, 170 B a pose), so one caller must not fill its quota.
#: Bursts of as many (a minute's registrations, a second's poses).
DEFAULT_REGISTRATION_RATE = 60.0
DEFAULT_POSE_WRITE_RATE = 50.0
#: Identities whose write buckets are kept; the longest idle is dropped past this.
MAX_TRACKED_WRITERS = 10_000
#: The largest value a record or pose DRVS writes may have, bytes (a record is about 1 KB): a
#: larger one is not read at all.
MAX_VALUE_BYTES = 16 * 1024


def _number(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name}: {_shown(value)} is not a finite number")
    return float(value)


def _integer(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name}: {_shown(value)} is not a whole number")
    return value


def _list(value: object, name: str, length: int | None = None) -> list[object]:
    if not isinstance(value, list) or (length is not None and len(value) != length):
        raise ValueError(f"{name}: {_shown(value)} is not a list{f' of {length}' if length is not None else ''}")
    return value


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


#: How each kind of field is read from JSON (by its annotation); fields of other kinds as they are.
_READERS: dict[str, Callable[[object, str], object]] = {
    "str": lambda v, n: v if isinstance(v, str) else _fail(n, v, "a string"),
    "float": _number,
    "int": _integer,
    "bool": lambda v, n: v if isinstance(v, bool) else _fail(n, v, "true or false"),
    "tuple[float, ...]": lambda v, n: tuple(_number(x, n) for x in _list(v, n)),
    "tuple[int, int]": lambda v, n: tuple(_integer(x, n) for x in _list(v, n, 2)),
    "tuple[str, ...]": lambda v, n: tuple(x if isinstance(x, str) else _fail(n, x, "a string") for x in _list(v, n)),
}


def _fail(name: str, value: object, what: str) -> Any:
    raise ValueError(f"{name}: {_shown(value)} is not {what}")


def _object(data: bytes) -> dict[str, Any]:
    """A JSON object of at most MAX_VALUE_BYTES; ValueError saying why not."""
    if len(data) > MAX_VALUE_BYTES:
        raise ValueError(f"{len(data)} bytes, more than the {MAX_VALUE_BYTES} a DRVS record may have")
    try:
        raw = json.loads(data)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"not UTF-8: {exc.reason}") from None
    if not isinstance(raw, dict):
        raise ValueError(f"JSON {type(raw).__name__}, not an object")
    return raw


def _fields(cls: Any, raw: dict[str, Any]) -> dict[str, Any]:
    """`raw`'s values for `cls`'s fields, each checked against its annotation; fields it does not
    know are left out (a newer server's), fields it lacks take their defaults (an older one's)."""
    out: dict[str, Any] = {}
    for f in fields(cls):
        if f.name in raw:
            read = _READERS.get(str(f.type))
            out[f.name] = read(raw[f.name], f.name) if read is not None else raw[f.name]
    return out


@dataclass(frozen=True)
class Record:
    """One camera's registration as the servers share it."""

    camera_id: str
    address: str
    homography: tuple[float, ...]
    image_size: tuple[int, int]
    detector_kinds: tuple[str, ...]
    max_range_m: float
    #: Who holds the id ("" anonymous), whose quota it counts against, the registration's secret
    #: as secret_digest keeps it (never the secret: whoever reads etcd cannot heartbeat for it).
    owner: str
    quota: str
    secret: str
    forward_secret: str
    #: The etcd lease the key is attached to (the camera's lease), and its TTL in seconds.
    lease: int = 0
    lease_ttl_s: float = 0.0
    #: The server that took the registration, and when (seconds since the Unix epoch).
    server: str = ""
    registered_at: float = 0.0
    #: The floor plan it registered in.
    frame: str = DEFAULT_FRAME
    #: A mobile camera (homography to its robot's base frame), and the pose lease it was granted.
    mobile: bool = False
    pose_lease_s: float = 0.0

    def encode(self) -> bytes:
        return json.dumps(asdict(self), sort_keys=True, separators=(",", ":")).encode()

    @classmethod
    def decode(cls, data: bytes) -> Record:
        """A record from etcd; ValueError (or TypeError: a field missing) when it is not one: too
        large, not JSON, nested too deeply, or a field of the wrong type."""
        return cls(**_fields(cls, _object(data)))

    def claim(self) -> Claim:
        """The id's hold as this record gives it: until the key goes (its lease decides)."""
        return Claim(self.owner, self.quota, self.secret, math.inf, self.forward_secret)


def secret_digest(secret: str) -> str:
    """What etcd keeps of a registration secret, and what a presented one is compared as: its
    SHA-256 (the secret is 24 random bytes: nothing to guess); "" for none."""
    return "sha256:" + hashlib.sha256(secret.encode()).hexdigest() if secret else ""


def key_of(camera_id: str) -> bytes:
    return PREFIX + camera_id.encode()


@dataclass(frozen=True)
class PoseRecord:
    """A mobile camera's pose as the server that took the update shares it."""

    x: float
    y: float
    yaw: float
    #: When it held (the camera's clock), and which server instance wrote it.
    time_unix: float
    origin: str

    def encode(self) -> bytes:
        return json.dumps(asdict(self), separators=(",", ":")).encode()

    @classmethod
    def decode(cls, data: bytes) -> PoseRecord:
        """A pose from etcd; ValueError or TypeError when it is not one (as Record.decode)."""
        return cls(**_fields(cls, _object(data)))


class WriteRate:
    """A token bucket per identity on the writes it causes in etcd: `rate` a `per_s` seconds, in
    bursts of as many. `take` counts one, or raises ResourceExhausted naming the limit, its flag
    and when to retry (nothing is counted then)."""

    def __init__(self, what: str, rate: float, per_s: float, flag: str, clock: Callable[[], float] = time.monotonic):
        if not rate > 0:
            raise ValueError(f"{flag}: must be > 0")
        self.what, self.flag, self._clock = what, flag, clock
        self.rate, self.burst, self.per_s = rate, max(1.0, rate), per_s
        self.rate_hz = rate / per_s
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()

    def check(self, identity: str) -> None:
        """Raise as `take` would, counting nothing: a caller over its rate is refused before any
        work is done for it (an etcd read, a field of view computed), not after."""
        self._count(identity, 0.0)

    def take(self, identity: str) -> None:
        self._count(identity, 1.0)

    def _count(self, identity: str, cost: float) -> None:
        now = self._clock()
        tokens, last = self._buckets.pop(identity, (self.burst, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate_hz)
        try:
            if tokens < 1.0:
                metrics.REGISTRY_WRITES_REFUSED.labels(self.what).inc()
                wait = round((1.0 - tokens) / self.rate_hz, 3)
                unit = "a minute" if self.per_s == 60 else "a second"
                raise ResourceExhausted(
                    f"{self.what}s: {identity} made more than {self.rate:g} "
                    f"{unit} (bursts of {self.burst:g}; {self.flag}) on the registry shared in etcd; "
                    f"retry in {wait:g} s",
                    retry_after_s=wait,
                )
            tokens -= cost
        finally:
            self._buckets[identity] = (tokens, now)
            while len(self._buckets) > MAX_TRACKED_WRITERS:
                self._buckets.popitem(last=False)


class SharedRegistry:
    """The etcd side of a server's registry: reads, compare-and-puts, lease renewals and deletes,
    and a watch that hands every change to the server (`apply` a record, `drop` an id, saying
    whether it lapsed: its lease ran out without it deregistering)."""

    def __init__(
        self,
        endpoints: Endpoints,
        apply: Callable[[Record], Any],
        drop: Callable[[str, str, bool], None],
        known: Callable[[], list[str]],
        *,
        apply_pose: Callable[[str, PoseRecord], Any] | None = None,
        client: EtcdClient | None = None,
        on_reachable: Callable[[bool], Awaitable[None]] | None = None,
        registration_rate: float = DEFAULT_REGISTRATION_RATE,
        pose_write_rate: float = DEFAULT_POSE_WRITE_RATE,
    ) -> None:
        self.endpoints = endpoints
        #: Writes to etcd per identity (the quota a registration counts against).
        self.registrations = WriteRate("registration", registration_rate, 60.0, "--registration-rate")
        self.pose_writes = WriteRate("pose update", pose_write_rate, 1.0, "--pose-write-rate")
        self.client = client or EtcdClient(endpoints)
        self._apply = apply
        self._drop = drop
        self._apply_pose = apply_pose
        #: This server instance, in the poses it writes (its own come back on the watch: skipped).
        self.origin = secrets.token_hex(6)
        self._pose_writes: dict[str, asyncio.Task[None]] = {}
        self._known = known
        #: Told whether etcd can be reached, each time that changes (the server's health says it).
        self._on_reachable = on_reachable
        self._task: asyncio.Task[None] | None = None
        #: Set once the prefix has been read (and again after every resynchronisation).
        self.synced = asyncio.Event()
        #: Why etcd cannot be reached now ("" when it can).
        self.trouble = ""
        self.records: dict[str, Record] = {}
        #: Deregistrations' markers seen: camera id -> the lease its deregistration ends.
        self.leaving: dict[str, int] = {}

    async def start(self) -> None:
        await self.client.start()
        self._task = asyncio.get_running_loop().create_task(self._follow())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
        await self.client.close()

    # --- what registration does ------------------------------------------------------------------

    async def get(self, camera_id: str) -> Record | None:
        """The id's current record in etcd (not this server's copy): who holds it now."""
        found = await self._guard(self.client.get(key_of(camera_id)))
        if found is None:
            return None
        return self._decode(found[0])

    async def put(self, record: Record, previous: Record | None, lease_ttl_s: float) -> Record:
        """Store `record` under a new lease of `lease_ttl_s`, only if the id still holds `previous`
        (None: only if it is free); the previous registration's lease is ended. FailedPrecondition
        when another server changed the id meanwhile; Unavailable while the watch is not following
        etcd (this server could not route what it registers)."""
        if self.trouble:
            raise Unavailable(f"registry: {self.trouble}; registrations wait until etcd answers")
        lease = await self._guard(self.client.grant(lease_ttl_s))
        stored = replace(record, lease=lease, lease_ttl_s=lease_ttl_s)
        expected = previous.encode() if previous is not None else None
        if not await self._guard(self.client.put_if(key_of(record.camera_id), stored.encode(), lease, expected)):
            await self._guard(self.client.revoke(lease))
            raise FailedPrecondition(
                f"camera_id: {record.camera_id!r} was registered through another server meanwhile; register again"
            )
        if previous is not None and previous.lease and previous.lease != lease:
            await self._guard(self.client.revoke(previous.lease))  # its key is on the new lease now
        return stored

    async def renew(self, record: Record) -> bool:
        """Keep the record's lease alive; False when it has run out (the key is gone)."""
        left: float = await self._guard(self.client.keep_alive(record.lease))
        return left > 0

    async def delete(self, record: Record) -> None:
        """Deregistration: the marker that says so first (every server then drops the camera as
        gone, not lost), then the key goes and its lease ends."""
        marker = await self._guard(self.client.grant(LEAVING_TTL_S))
        await self._guard(self.client.put(LEAVING + record.camera_id.encode(), str(record.lease).encode(), marker))
        await self._guard(self.client.delete(key_of(record.camera_id)))
        await self._guard(self.client.revoke(record.lease))

    def admit_pose(self, camera_id: str) -> None:
        """Before a pose update of `camera_id` is taken: ResourceExhausted when the identity holding
        it (as its record says) sends them faster than --pose-write-rate allows."""
        record = self.records.get(camera_id)
        if record is not None:
            self.pose_writes.take(record.quota)

    def share_pose(self, camera_id: str, pose: PoseRecord) -> None:
        """Write a mobile camera's pose for the other servers, on its lease, without waiting; if a
        write for it is still on its way, this one replaces it (only the newest matters)."""
        record = self.records.get(camera_id)
        if record is None:
            return
        running = self._pose_writes.get(camera_id)
        if running is not None and not running.done():
            running.cancel()
        task = asyncio.get_running_loop().create_task(self._put_pose(record, pose))
        self._pose_writes[camera_id] = task

    async def _put_pose(self, record: Record, pose: PoseRecord) -> None:
        try:
            await self.client.put(POSES + record.camera_id.encode(), pose.encode(), record.lease)
        except Unavailable as exc:
            log.warning("registry: camera %s's pose not shared: %s", record.camera_id, exc)
        finally:
            self._pose_writes.pop(record.camera_id, None)

    async def _guard(self, call: Any) -> Any:
        try:
            return await call
        except Unavailable as exc:
            raise Unavailable(f"registry: {exc}; registrations wait until etcd answers") from None

    # --- the watch -------------------------------------------------------------------------------

    def _decode(self, data: bytes, key: bytes = b"") -> Record | None:
        try:
            return Record.decode(data)
        except (ValueError, TypeError) as exc:
            _skipped(key or b"a camera record", "camera", exc)
            return None

    def _take(self, event: Event) -> bool:
        """Apply one change; False when its value is not a record DRVS can use (logged, counted in
        drvs_registry_records_skipped_total, and skipped: a camera it replaced leaves routing)."""
        if event.key.startswith(POSES):
            self._take_pose(event)
            return True
        if event.key.startswith(LEAVING):
            if event.kind == "put":  # (its own deletion, when its lease ends, changes nothing)
                with contextlib.suppress(ValueError):
                    self.leaving[event.key[len(LEAVING) :].decode(errors="replace")] = int(event.value)
            return True
        if not event.key.startswith(PREFIX):
            return True
        camera_id = event.key[len(PREFIX) :].decode(errors="replace")
        if event.kind == "delete":
            record = self.records.pop(camera_id, None)
            if record is not None:
                if self.leaving.pop(camera_id, None) == record.lease:
                    self._drop(camera_id, "deregistered (the shared registry says so)", False)
                else:
                    self._drop(camera_id, "its lease ran out without it deregistering", True)
            return True
        record = self._decode(event.value, event.key)
        if record is not None and record.camera_id != camera_id:
            _skipped(event.key, "camera", ValueError(f"camera_id: {record.camera_id[:80]!r} is not the key's"))
            record = None
        if record is None:
            if self.records.pop(camera_id, None) is not None:  # what it replaced is no registration now
                # (not deregistered: the safe side is to report its floor unseen, as a lapse)
                self._drop(camera_id, "its record in etcd was replaced by one that is not a record", True)
            return False
        previous = self.records.get(camera_id)
        if previous == record:
            return True  # this server's own write, already applied
        if self.leaving.get(camera_id, record.lease) != record.lease:
            del self.leaving[camera_id]  # an earlier registration's: this one has not left
        self.records[camera_id] = record
        try:
            self._apply(record)
        except Exception as exc:  # one record refused here must not stop the watch
            del self.records[camera_id]
            if previous is not None:  # the registration it replaced is gone from etcd
                self._drop(camera_id, f"its new record in the shared registry was refused here: {exc}", True)
            if not isinstance(exc, DrvsError):
                _skipped(event.key, "camera", exc)
                return False
            log.warning("registry: camera %s's record in etcd was refused here: %s", camera_id, exc)
        return True

    def _take_pose(self, event: Event) -> None:
        if event.kind != "put" or self._apply_pose is None:
            return  # a pose goes with its camera's key: nothing to do on its own
        camera_id = event.key[len(POSES) :].decode(errors="replace")
        try:
            pose = PoseRecord.decode(event.value)
        except (ValueError, TypeError) as exc:
            _skipped(event.key, "pose", exc)
            return
        if pose.origin == self.origin or camera_id not in self.records:
            return
        try:
            self._apply_pose(camera_id, pose)
        except DrvsError as exc:
            log.debug("registry: camera %s's pose from etcd not applied: %s", camera_id, exc)
        except Exception as exc:  # as in _take
            _skipped(event.key, "pose", exc)

    async def _resync(self) -> int:
        """Read the whole prefix: apply what is there (cameras, then their poses), drop what is
        not (as lost, unless a marker says it deregistered); the revision read at."""
        kvs, revision = await self.client.get_prefix(ROOT)
        present: set[str] = set()
        kvs.sort(key=lambda kv: not kv[0].startswith(PREFIX))  # cameras before poses
        for key, value, lease in kvs:
            if self._take(Event("put", key, value, lease, revision)) and key.startswith(PREFIX):
                present.add(key[len(PREFIX) :].decode(errors="replace"))
        for camera_id in [c for c in self._known() if c not in present]:
            record = self.records.pop(camera_id, None)
            left = record is not None and self.leaving.pop(camera_id, None) == record.lease
            if left:
                self._drop(camera_id, "deregistered while etcd could not be reached", False)
            else:
                self._drop(camera_id, "gone from the shared registry, not deregistered, when it was read again", True)
        return revision

    async def _follow(self) -> None:
        backoff = Backoff(INITIAL_BACKOFF_S, MAX_BACKOFF_S)
        while True:
            try:
                revision = await self._resync()
                if self.trouble:
                    log.warning("registry: etcd %s answers again; resynchronised (%d cameras)", self.endpoints,
                                len(self.records))  # fmt: skip
                    self.trouble = ""
                    if self._on_reachable is not None:
                        await self._on_reachable(True)
                self.synced.set()
                backoff.reset()
                async for event in self.client.watch_prefix(ROOT, revision + 1):
                    self._take(event)
                raise Unavailable(f"etcd {self.endpoints}: the watch ended")
            except Unavailable as exc:
                await self._lost("etcd unreachable", str(exc) or "etcd unreachable")
            except Exception as exc:  # the watch must not die: restarted, health says so
                log.exception("registry: the watch of etcd %s failed; restarting it", self.endpoints)
                metrics.REGISTRY_WATCH_RESTARTS.inc()
                await self._lost("the watch failed", f"the watch of etcd {self.endpoints} failed ({exc!r})")
            await backoff.sleep()

    async def _lost(self, what: str, why: str) -> None:
        """The watch stopped (`why`): route on what is known, refuse registrations (health says
        NOT_SERVING for them) until it is back."""
        if not self.trouble:
            log.warning(
                "registry: %s (%s): routing on the last registry known (%d cameras); "
                "registrations are refused until it answers",
                what,
                why,
                len(self.records),
            )
            self.trouble = why
            if self._on_reachable is not None:
                await self._on_reachable(False)
        self.trouble = why
        self.synced.clear()


def _skipped(key: bytes, kind: str, exc: BaseException) -> None:
    """A value under DRVS's prefix that is not one DRVS wrote (or one this server cannot apply):
    logged, counted, and skipped."""
    metrics.REGISTRY_SKIPPED.labels(kind).inc()
    log.warning(
        "registry: %s in etcd is not one DRVS can read (%s); skipped",
        key[:120].decode(errors="replace"),
        str(exc)[:200],
    )
