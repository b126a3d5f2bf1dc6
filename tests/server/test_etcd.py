"""drvs.server.etcd against real etcd processes (Debian's etcd-server, started on free ports and reaped):
keys under a prefix, leases that expire on their own, compare-and-put, watches from a revision,
and a three-member cluster that keeps answering through the client's one channel when a member
dies."""

from __future__ import annotations

import asyncio
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
import pytest_asyncio
from grpc import aio

from drvs.core.errors import InvalidArgument, Unavailable
from drvs.server.etcd import Endpoints, EtcdClient, Event, wait_ready
from drvs.tools.launch import EtcdMember, start_etcd

pytestmark = pytest.mark.skipif(
    shutil.which("etcd") is None, reason="etcd is not installed (./run test installs it as root)"
)


def endpoints(members: list[EtcdMember]) -> Endpoints:
    return Endpoints.parse("etcd://" + ",".join(m.address for m in members))


@pytest_asyncio.fixture
async def one(tmp_path: Path) -> AsyncIterator[list[EtcdMember]]:
    members = await start_etcd(tmp_path)
    try:
        yield members
    finally:
        for m in members:
            await m.stop()


async def test_keys_leases_and_compare_and_put(one: list[EtcdMember]) -> None:
    async with EtcdClient(endpoints(one)) as etcd:
        lease = await etcd.grant(1.2)  # whole seconds: 2
        await etcd.put(b"/drvs/t/a", b"1", lease)
        await etcd.put(b"/drvs/t/b", b"2")
        await etcd.put(b"/drvs/u", b"elsewhere")
        kvs, revision = await etcd.get_prefix(b"/drvs/t/")
        assert [(k, v) for k, v, _ in kvs] == [(b"/drvs/t/a", b"1"), (b"/drvs/t/b", b"2")] and revision > 0
        assert (await etcd.get(b"/drvs/t/a")) == (b"1", lease)
        # Compare-and-put: only the holder of the expected value replaces it; absent means absent.
        assert await etcd.put_if(b"/drvs/t/b", b"3", 0, expected=b"2")
        assert not await etcd.put_if(b"/drvs/t/b", b"4", 0, expected=b"2")
        assert not await etcd.put_if(b"/drvs/t/b", b"5", 0, expected=None)
        assert await etcd.put_if(b"/drvs/t/c", b"6", 0, expected=None)
        assert (await etcd.get(b"/drvs/t/b")) == (b"3", 0)
        # A lease kept alive keeps its key; revoked, its key goes.
        assert await etcd.keep_alive(lease) >= 1
        await etcd.revoke(lease)
        assert await etcd.get(b"/drvs/t/a") is None
        assert await etcd.keep_alive(lease) == 0  # gone
        assert await etcd.delete(b"/drvs/t/c") and not await etcd.delete(b"/drvs/t/c")


async def test_a_watch_sees_puts_deletes_and_expiries_in_order(one: list[EtcdMember]) -> None:
    async with EtcdClient(endpoints(one)) as writer, EtcdClient(endpoints(one)) as reader:
        _, revision = await reader.get_prefix(b"/drvs/w/")
        seen: list[Event] = []
        done = asyncio.Event()

        async def watch() -> None:
            async for event in reader.watch_prefix(b"/drvs/w/", revision + 1):
                seen.append(event)
                if len(seen) == 4:
                    done.set()

        watching = asyncio.get_running_loop().create_task(watch())
        try:
            lease = await writer.grant(1)
            await writer.put(b"/drvs/w/cam1", b"v1", lease)
            await writer.put(b"/drvs/w/cam2", b"v2")
            await writer.delete(b"/drvs/w/cam2")
            # Nobody keeps cam1's lease alive: etcd deletes its key when the lease runs out.
            await asyncio.wait_for(done.wait(), 15)
        finally:
            watching.cancel()
        assert [(e.kind, e.key) for e in seen] == [
            ("put", b"/drvs/w/cam1"),
            ("put", b"/drvs/w/cam2"),
            ("delete", b"/drvs/w/cam2"),
            ("delete", b"/drvs/w/cam1"),
        ]
        assert seen[0].lease == lease and seen[0].value == b"v1"
        assert [e.revision for e in seen] == sorted(e.revision for e in seen)


async def test_a_three_member_cluster_answers_through_one_channel_when_a_member_dies(tmp_path: Path) -> None:
    members = await start_etcd(tmp_path, members=3)
    try:
        async with EtcdClient(endpoints(members), timeout_s=3.0) as etcd:
            await etcd.put(b"/drvs/c/k", b"before")
            members[0].kill()  # SIGKILL: no goodbye to the others
            # The channel's other addresses answer; the two left keep a quorum and take writes (once
            # they have elected a leader, if the dead member led: a write meanwhile times out).
            deadline = asyncio.get_running_loop().time() + 20
            while True:
                try:
                    await etcd.put(b"/drvs/c/k", b"after")
                    break
                except Unavailable:
                    assert asyncio.get_running_loop().time() < deadline
            assert (await etcd.get(b"/drvs/c/k")) == (b"after", 0)
    finally:
        for m in members:
            await m.stop()


async def test_reads_a_failing_member_drops_go_again_and_writes_do_not(one: list[EtcdMember]) -> None:
    """A member that fails every call UNAVAILABLE (a real gRPC server on etcd's KV service, listed
    beside a real etcd: what a member killed with calls on its connection answers) costs a read
    nothing, the client sends it again and the channel's round robin takes it to etcd, while a
    write that landed there fails once, not sent again (it might have been applied)."""
    seen: dict[str, int] = {"Range": 0, "Put": 0}

    def failing(name: str) -> grpc.RpcMethodHandler[bytes, bytes]:
        async def handle(request: bytes, context: aio.ServicerContext[bytes, bytes]) -> bytes:
            seen[name] += 1
            await context.abort(grpc.StatusCode.UNAVAILABLE, "Stream removed")
            raise AssertionError("abort returns no answer")

        return grpc.unary_unary_rpc_method_handler(handle)

    dying = aio.server()
    dying.add_generic_rpc_handlers(
        [grpc.method_handlers_generic_handler("etcdserverpb.KV", {n: failing(n) for n in seen})]
    )
    port = dying.add_insecure_port("127.0.0.1:0")
    await dying.start()
    try:
        both = Endpoints.parse(f"etcd://{one[0].address},127.0.0.1:{port}")
        async with EtcdClient(both, timeout_s=5.0) as etcd:
            await wait_ready(endpoints(one), 10.0)
            written = failed = 0
            while not written:  # a write: sent once, wherever the channel picks
                try:
                    await etcd.put(b"/drvs/r/k", b"v")
                    written += 1
                except Unavailable as exc:
                    assert "UNAVAILABLE" in str(exc) and f"127.0.0.1:{port}" in str(exc)
                    failed += 1
            for _ in range(40):  # reads, until the failing member has failed three of them
                assert (await etcd.get(b"/drvs/r/k")) == (b"v", 0)
                assert (await etcd.get_prefix(b"/drvs/r/"))[0] == [(b"/drvs/r/k", b"v", 0)]
                if seen["Range"] >= 3:
                    break
            assert seen["Range"] >= 3, seen  # the reads did meet the failing member, and went again
            assert seen["Put"] == failed  # each failed write was sent once
    finally:
        await dying.stop(None)


async def test_etcd_gone_is_unavailable_naming_the_endpoints(tmp_path: Path) -> None:
    members = await start_etcd(tmp_path)
    await members[0].stop()
    async with EtcdClient(endpoints(members), timeout_s=0.5) as etcd:
        with pytest.raises(Unavailable, match=r"etcd etcd://127\.0\.0\.1:\d+: put: "):
            await etcd.put(b"/drvs/x", b"1")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("http://127.0.0.1:2379", r"registry: 'http://127\.0\.0\.1:2379' is not etcd://HOST:PORT"),
        ("etcd://", "names an empty etcd endpoint"),
        ("etcd://127.0.0.1:2379,", "names an empty etcd endpoint"),
        ("etcd://127.0.0.1", "registry: '127.0.0.1' is not host:port"),
    ],
)
def test_bad_endpoints_are_refused(text: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        Endpoints.parse(text)


def test_endpoints_become_one_grpc_target() -> None:
    assert Endpoints.parse("etcd://10.0.0.1:2379,10.0.0.2:2379").target() == "ipv4:10.0.0.1:2379,10.0.0.2:2379"
    assert Endpoints.parse("etcd://etcd.example:2379").target() == "etcd.example:2379"  # DNS: every address
    with pytest.raises(InvalidArgument, match="registry: several addresses must all be IPv4 or all IPv6"):
        Endpoints.parse("etcd://a.example:2379,b.example:2379").target()
