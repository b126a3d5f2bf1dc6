"""Camera-id ownership (drvs.server.registry.Claims) as a property: whatever several identities do to the
same few ids, in any order, no identity registers, renews or deregisters an id another holds, and
every refusal changes nothing."""

from __future__ import annotations

import asyncio

import grpc
import pytest
from grpc import aio
from hypothesis import given, settings
from hypothesis import strategies as st

from drvs.core.errors import FailedPrecondition, NotFound, PermissionDenied, ResourceExhausted
from drvs.server import DrvsServer
from drvs.server.claims import Claims
from drvs.v1 import registry_pb2, registry_pb2_grpc
from tests.helpers import register_message

LEASE = 5.0
GRACE = 2.0
#: Two credentials and two anonymous callers (who differ only in what secrets they know).
CALLERS = ("token:lobby", "token:yard", "anon-1", "anon-2")
IDS = ("a", "b", "c")


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def owner_of(caller: str) -> str:
    return "" if caller.startswith("anon") else caller


def quota_of(caller: str) -> str:
    return caller  # anonymous callers count against their address; one each here


ops = st.lists(
    st.tuples(
        st.sampled_from(("register", "heartbeat", "deregister", "wait")),
        st.sampled_from(CALLERS),
        st.sampled_from(IDS),
        st.sampled_from(("own", "stale", "none", "stolen")),
        st.floats(0.0, 4.0),
    ),
    max_size=60,
)


@settings(max_examples=300, deadline=None)
@given(ops)
def test_no_identity_can_affect_another_identitys_camera_ids(steps: list[tuple[str, str, str, str, float]]) -> None:
    clock = Clock()
    claims = Claims(grace_s=GRACE, max_per_identity=2, clock=clock)
    # What each caller knows: the secrets of the registrations it made itself (newest last).
    known: dict[tuple[str, str], list[str]] = {}
    for op, caller, camera_id, which, dt in steps:
        if op == "wait":
            clock.now += dt
            claims.expire()
            continue
        mine = known.get((caller, camera_id), [])
        others = [s for (c, i), ss in known.items() if i == camera_id and c != caller for s in ss]
        secret = {
            "own": mine[-1] if mine else "",
            "stale": mine[0] if mine else "",
            "none": "",
            # A secret another caller was given: it leaks only if the rule lets it act for the holder.
            "stolen": others[-1] if others else "",
        }[which]
        before = claims.holder(camera_id)
        snapshot = None if before is None else (before.owner, before.secret, before.until, before.forward_secret)
        forward = f"forward-{caller}"  # each caller's own process secret
        owner = owner_of(caller)
        try:
            if op == "register":
                claims.check_register(camera_id, owner, secret, quota_of(caller), forward)
                new = claims.grant(camera_id, owner, quota_of(caller), clock.now + LEASE, forward)
                known.setdefault((caller, camera_id), []).append(new)
                # Allowed only on a free id, by the same credential, or (anonymous) with the secret.
                assert snapshot is None or (
                    snapshot[0] == owner and bool(owner or secret == snapshot[1] or forward == snapshot[3])
                )
            else:
                claims.check(camera_id, owner, secret)
                assert before is not None and before.owner == owner and secret == before.secret
                if op == "heartbeat":
                    claims.renew(camera_id, clock.now + LEASE)
                else:
                    claims.release(camera_id)
        except (PermissionDenied, FailedPrecondition, NotFound, ResourceExhausted) as exc:
            after = claims.holder(camera_id)
            kept = None if after is None else (after.owner, after.secret, after.until, after.forward_secret)
            assert kept == snapshot, exc
            if isinstance(exc, PermissionDenied):
                assert before is not None and str(exc).startswith(f"camera_id: {camera_id!r} belongs to another")
        # No credential ever holds more than its cap.
        for caller_name in CALLERS:
            assert claims.held_by(quota_of(caller_name)) <= 2


def test_a_claim_lapses_exactly_after_lease_plus_grace() -> None:
    clock = Clock()
    claims = Claims(grace_s=GRACE, clock=clock)
    claims.grant("a", "token:yard", "token:yard", LEASE)
    clock.now = LEASE + GRACE - 0.01
    with pytest.raises(PermissionDenied, match=r"until \d\d:\d\d:\d\d UTC \(0 s from now\)"):
        claims.check_register("a", "token:lobby", "", "token:lobby")
    clock.now = LEASE + GRACE
    claims.check_register("a", "token:lobby", "", "token:lobby")


def test_an_anonymous_camera_whose_reply_was_lost_proves_itself_with_its_forward_secret() -> None:
    """Its Register reached the server but the reply (with the new secret) did not reach it: it
    registers again with the same forward secret, which only it and the server know."""
    clock = Clock()
    claims = Claims(grace_s=GRACE, clock=clock)
    claims.grant("a", "", "127.0.0.1", LEASE, "forward-real")
    claims.check_register("a", "", "", "127.0.0.1", "forward-real")
    for forward in ("", "forward-other"):
        with pytest.raises(PermissionDenied, match="does not carry its registration_secret"):
            claims.check_register("a", "", "", "127.0.0.2", forward)


# --- the same, black-box: a real server on a real socket, two credentials -------------------------

TOKENS = {"lobby": "lobby-token-0123456789abcdef", "yard": "yard-token-fedcba9876543210"}
ADDRESSES = {"lobby": "127.0.0.1:1001", "yard": "127.0.0.1:1002"}

server_ops = st.lists(
    st.tuples(
        st.sampled_from(("register", "heartbeat", "deregister")),
        st.sampled_from(tuple(TOKENS)),
        st.sampled_from(IDS),
        st.sampled_from(("own", "none", "stolen")),
    ),
    min_size=1,
    max_size=25,
)


@settings(max_examples=40, deadline=None)
@given(server_ops)
def test_over_the_wire_no_credential_moves_or_drops_another_credentials_camera(
    steps: list[tuple[str, str, str, str]],
) -> None:
    """Whatever two camera credentials send about the same ids, an id listed by the server is at the
    address of the credential that holds it, and every call on an id held by the other fails."""
    asyncio.run(_exercise_server(steps))


async def _exercise_server(steps: list[tuple[str, str, str, str]]) -> None:
    tables = {token: name for name, token in TOKENS.items()}
    async with (
        DrvsServer("127.0.0.1:0", lease_ttl_s=600, camera_tokens=tables, robot_tokens=None) as server,
        aio.insecure_channel(server.address) as channel,
    ):
        stub = registry_pb2_grpc.RegisterVisionServiceStub(channel)
        holder: dict[str, str] = {}  # id -> credential, as the server should see it
        secrets: dict[tuple[str, str], str] = {}  # (credential, id) -> the secret it was last given
        for op, who, camera_id, which in steps:
            other = next(n for n in TOKENS if n != who)
            secret = {
                "own": secrets.get((who, camera_id), ""),
                "none": "",
                "stolen": secrets.get((other, camera_id), ""),
            }[which]
            metadata = (("authorization", f"Bearer {TOKENS[who]}"),)
            try:
                if op == "register":
                    message = register_message(camera_id)
                    message.address = ADDRESSES[who]
                    message.registration_secret = secret
                    reply = await stub.Register(message, metadata=metadata)
                    secrets[(who, camera_id)] = reply.registration_secret
                    assert holder.get(camera_id, who) == who
                    holder[camera_id] = who
                elif op == "heartbeat":
                    beat = registry_pb2.HeartbeatRequest(camera_id=camera_id, registration_secret=secret)
                    await stub.Heartbeat(beat, metadata=metadata)
                    assert holder.get(camera_id) == who
                else:
                    bye = registry_pb2.DeregisterRequest(camera_id=camera_id, registration_secret=secret)
                    await stub.Deregister(bye, metadata=metadata)
                    assert holder.pop(camera_id) == who
            except aio.AioRpcError as exc:
                expected = {grpc.StatusCode.PERMISSION_DENIED, grpc.StatusCode.FAILED_PRECONDITION}
                expected.add(grpc.StatusCode.NOT_FOUND)
                assert exc.code() in expected, (exc.code(), exc.details())
                if holder.get(camera_id) == other:
                    assert exc.code() == grpc.StatusCode.PERMISSION_DENIED
            listed = {c.camera_id: c.address for c in server.registry.cameras()}
            assert listed == {cid: ADDRESSES[name] for cid, name in holder.items()}
