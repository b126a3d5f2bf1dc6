"""Who holds a camera id: the registry's claims, held by leases plus a grace period. Pure logic."""

from __future__ import annotations

import hmac
import math
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass

from drvs.core.errors import FailedPrecondition, NotFound, PermissionDenied, ResourceExhausted

#: How long a camera id stays with whoever registered it after its lease ran out: the real camera
#: gets it back after a network blip, and a squatter loses it this long after it stops renewing.
DEFAULT_GRACE_S = 10.0
#: Camera ids one identity (a credential; without one, a peer IP) may hold at once.
DEFAULT_MAX_CAMERAS_PER_IDENTITY = 1000


@dataclass
class Claim:
    """Who holds a camera id: their identity ("" when anonymous), whom the id counts against, the
    secret of the current registration, and when the hold lapses (lease end plus grace)."""

    owner: str
    quota: str
    secret: str
    until: float
    #: The forward secret the registration handed over: the same camera process sends it again.
    forward_secret: str = ""


class Claims:
    """Camera ids and who holds them. Pure logic, on the registry's clock.

    An id belongs to the identity that registered it until its lease ends plus a grace period.
    While held, a different identity may not register, renew or deregister it; the same identity
    may register it again (a new registration, with a new secret). Anonymous callers cannot be
    told apart, so for them the proof is the secret: replacing a held anonymous registration
    needs the secret of the current one. Heartbeats and deregistrations always need it.
    """

    def __init__(
        self,
        grace_s: float = DEFAULT_GRACE_S,
        max_per_identity: int = DEFAULT_MAX_CAMERAS_PER_IDENTITY,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        if grace_s < 0 or max_per_identity < 1:
            raise ValueError("grace_s must be >= 0 and max_per_identity >= 1")
        self.grace_s = grace_s
        self.max_per_identity = max_per_identity
        self._clock = clock
        self._wall_clock = wall_clock
        self._claims: dict[str, Claim] = {}
        self._held: dict[str, set[str]] = {}
        #: Ids whose registration is on its way (a registry shared in etcd), by quota: they count.
        self._reserved: dict[str, set[str]] = {}

    def __contains__(self, camera_id: object) -> bool:
        return camera_id in self._claims

    def holder(self, camera_id: str) -> Claim | None:
        claim = self._claims.get(camera_id)
        if claim is not None and claim.until <= self._clock():
            self.release(camera_id)
            return None
        return claim

    def held_by(self, quota: str, besides: str = "") -> int:
        """Ids `quota` holds or has reserved, `besides` left out."""
        ids = self._held.get(quota, set()) | self._reserved.get(quota, set())
        return len(ids - {besides})

    def reserve(self, camera_id: str, quota: str) -> None:
        """Count `camera_id` against `quota` while its registration is on its way (check_register,
        then this, with no await between: concurrent registrations cannot all pass the cap);
        `unreserve` once it is granted or failed."""
        self._reserved.setdefault(quota, set()).add(camera_id)

    def unreserve(self, camera_id: str, quota: str) -> None:
        reserved = self._reserved.get(quota)
        if reserved is not None:
            reserved.discard(camera_id)
            if not reserved:
                del self._reserved[quota]

    def _until(self, claim: Claim) -> str:
        if math.isinf(claim.until):  # a registry shared in etcd: its lease there decides
            return "while its registration's lease in the shared registry lasts"
        left = max(0.0, claim.until - self._clock())
        at = time.strftime("%H:%M:%S", time.gmtime(self._wall_clock() + left))
        return f"until {at} UTC ({left:.0f} s from now) unless it renews its lease"

    def check_register(self, camera_id: str, owner: str, proof: str, quota: str, forward_secret: str = "") -> None:
        """May `owner` register `camera_id` now? Raises PermissionDenied / ResourceExhausted.

        An anonymous caller proves it holds the id with the current registration's secret, or by
        sending the same forward secret again: the same camera process whose reply was lost."""
        claim = self.holder(camera_id)
        if claim is not None:
            if claim.owner != owner:
                raise PermissionDenied(f"camera_id: {camera_id!r} belongs to another credential {self._until(claim)}")
            proven = bool(proof) and hmac.compare_digest(proof.encode(), claim.secret.encode())
            same = bool(forward_secret) and hmac.compare_digest(forward_secret.encode(), claim.forward_secret.encode())
            if not owner and not (proven or same):
                raise PermissionDenied(
                    f"camera_id: {camera_id!r} belongs to another credential (an anonymous registration; "
                    f"this request does not carry its registration_secret) {self._until(claim)}"
                )
        if (claim is None or claim.quota != quota) and self.held_by(quota, camera_id) >= self.max_per_identity:
            raise ResourceExhausted(
                f"registrations: {quota} already holds {self.held_by(quota, camera_id)} camera ids "
                f"(limit {self.max_per_identity} per identity, --max-cameras-per-identity)"
            )

    def grant(self, camera_id: str, owner: str, quota: str, lease_until: float, forward_secret: str = "") -> str:
        """Give `camera_id` to `owner` with a new registration secret (check_register first)."""
        self.release(camera_id)
        secret = secrets.token_urlsafe(24)
        self._claims[camera_id] = Claim(owner, quota, secret, lease_until + self.grace_s, forward_secret)
        self._held.setdefault(quota, set()).add(camera_id)
        return secret

    def check(self, camera_id: str, owner: str, secret: str) -> None:
        """May this call act for `camera_id`'s current registration (heartbeat, deregister)?"""
        claim = self.holder(camera_id)
        if claim is None:
            raise NotFound(f"camera_id: {camera_id!r} is not registered")
        if claim.owner != owner:
            raise PermissionDenied(f"camera_id: {camera_id!r} belongs to another credential {self._until(claim)}")
        if not (secret and hmac.compare_digest(secret.encode(), claim.secret.encode())):
            raise FailedPrecondition(
                f"registration_secret: {'empty' if not secret else 'not the current one'} for camera_id "
                f"{camera_id!r}: another registration of this id replaced it, or it never was; register again"
            )

    def adopt(self, camera_id: str, claim: Claim | None) -> None:
        """Hold `camera_id` as another server recorded it (a shared registry), or free it (None)."""
        self.release(camera_id)
        if claim is not None:
            self._claims[camera_id] = claim
            self._held.setdefault(claim.quota, set()).add(camera_id)

    def renew(self, camera_id: str, lease_until: float) -> None:
        claim = self._claims.get(camera_id)
        if claim is not None:
            claim.until = lease_until + self.grace_s

    def release(self, camera_id: str) -> None:
        claim = self._claims.pop(camera_id, None)
        if claim is not None:
            held = self._held.get(claim.quota)
            if held is not None:
                held.discard(camera_id)
                if not held:
                    del self._held[claim.quota]

    def expire(self) -> list[str]:
        """Drop every hold that has lapsed; returns their ids."""
        now = self._clock()
        gone = [cid for cid, claim in self._claims.items() if claim.until <= now]
        for cid in gone:
            self.release(cid)
        return gone
