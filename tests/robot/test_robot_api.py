"""The robot programmer's API (drvs.robot, re-exported from drvs), against real server and camera processes."""

from __future__ import annotations

import ast
import asyncio
import itertools
import logging
import math
import pydoc
import re
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from grpc import aio

import drvs
from drvs.core import errors, model
from drvs.core.errors import DrvsError, InvalidArgument, Unavailable
from drvs.core.model import CameraError, DetectionReport
from drvs.robot import DrvsClient, RetryPolicy
from drvs.tools.launch import ManagedProcess, start_server
from drvs.v1 import registry_pb2_grpc
from tests.helpers import BOTH_REGION, CAM1_REGION, YELLOW, Office, register_message


@pytest.fixture
def refused_address() -> Iterator[str]:
    """A loopback address where nothing listens (bound, never listening: connections are refused)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    try:
        yield f"127.0.0.1:{s.getsockname()[1]}"
    finally:
        s.close()


# --- connecting --------------------------------------------------------------------------------------


async def test_connect_fails_fast_naming_the_address(refused_address: str) -> None:
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    with pytest.raises(Unavailable, match=refused_address) as caught:
        await DrvsClient.connect(refused_address, connect_timeout_s=30)
    # Refused at once: not after the 30 s deadline.
    assert loop.time() - t0 < 10
    assert caught.value.code == "UNAVAILABLE" and caught.value.camera_id is None
    with pytest.raises(Unavailable, match=refused_address):
        async with DrvsClient.connect(refused_address, robot_id="r"):
            raise AssertionError("entered the block without a server")


async def test_connect_gives_up_on_a_silent_server_after_its_deadline() -> None:
    """A peer that accepts TCP and never answers: connect_timeout_s bounds the attempt."""
    held: list[asyncio.StreamWriter] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        held.append(writer)

    black_hole = await asyncio.start_server(hold, "127.0.0.1", 0)
    address = f"127.0.0.1:{black_hole.sockets[0].getsockname()[1]}"
    try:
        with pytest.raises(Unavailable, match=rf"server {address}: not reachable within 0.5 s"):
            await DrvsClient.connect(address, connect_timeout_s=0.5)
    finally:
        for writer in held:
            writer.close()
        black_hole.close()
        await black_hole.wait_closed()


async def test_connect_returns_a_started_client_of_a_real_server() -> None:
    server, address = await start_server()
    try:
        drvs_client = await DrvsClient.connect(address, robot_id="r")
        try:
            # The report listener starts with the first per-camera request, not before.
            assert drvs_client.port == 0 and not drvs_client.listening and await drvs_client.cameras() == []
            await drvs_client.detect(YELLOW, (0, 0, 1, 1), timeout_s=1)
            assert drvs_client.listening and drvs_client.port > 0
        finally:
            await drvs_client.close()
        await drvs_client.close()  # closing again does nothing
        with pytest.raises(DrvsError, match="not started"):
            await drvs_client.cameras()
        async with DrvsClient.connect(address, robot_id="r", listen="127.0.0.1:0") as robot:
            assert robot.callback_address == f"127.0.0.1:{robot.port}"
            result = await robot.detect(YELLOW, (0, 0, 1, 1), timeout_s=1)
            assert result.camera_ids == () and result.complete
    finally:
        assert await server.stop() == 0


async def test_wrong_python_types_are_invalid_arguments_naming_the_argument() -> None:
    """Robot code's Python mistakes (a number for the filter, an id or a frame, a string or a number
    for the region) raise InvalidArgument naming the argument and the type given, not a TypeError
    from inside the client (or, for robot_id, nothing until a request carried it); the client goes on
    serving the next request."""
    server, address = await start_server()
    try:
        wrong_id: Any = 5
        with pytest.raises(InvalidArgument, match=r"^robot_id: expected a string, got int$"):
            DrvsClient(address, robot_id=wrong_id)
        with pytest.raises(InvalidArgument, match=r"^frame: expected a string, got int$"):
            DrvsClient(address, frame=wrong_id)
        async with DrvsClient.connect(address, robot_id="r") as robot:
            with pytest.raises(InvalidArgument, match=r"^filter_def: expected a string, got int$"):
                await robot.detect(123, (0, 0, 1, 1))  # type: ignore[call-overload]
            with pytest.raises(InvalidArgument, match=r"^request_id: expected a string, got int$"):
                await robot.detect(YELLOW, (0, 0, 1, 1), request_id=wrong_id)
            with pytest.raises(InvalidArgument, match=r"^frame: expected a string, got int$"):
                await robot.cameras(frame=wrong_id)
            wrong: list[tuple[Any, str]] = [("0,0,1,1", "str"), (5, "int"), (None, "NoneType")]
            for region, kind in wrong:
                with pytest.raises(InvalidArgument, match=rf"^region: expected a shapely Polygon, .*, got {kind}$"):
                    await robot.detect(YELLOW, region)
                with pytest.raises(InvalidArgument, match=rf", got {kind}$"):
                    robot.track(YELLOW, region, rate_hz=5, duration_s=1)  # refused as it is asked for
            assert (await robot.detect(YELLOW, (0, 0, 1, 1), timeout_s=1)).complete
    finally:
        assert await server.stop() == 0


def test_constructing_a_client_does_no_network_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """No name is resolved and no socket is opened until the client starts."""

    def no_network(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("network work while constructing a client")

    monkeypatch.setattr(socket, "getaddrinfo", no_network)
    monkeypatch.setattr(socket.socket, "connect", no_network)
    client = DrvsClient("drvs.example:50051", robot_id="r")
    connecting = DrvsClient.connect("drvs.example:50051", robot_id="r")
    assert client.listen == "" and client.port == 0
    assert connecting.client.listen == ""
    # Bad arguments are still refused at once.
    with pytest.raises(InvalidArgument, match=r"^server: "):
        DrvsClient("no-port")
    with pytest.raises(InvalidArgument, match=r"^connect_timeout_s: "):
        DrvsClient.connect("drvs.example:50051", connect_timeout_s=0)


# --- retry ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"attempts": 0}, r"^retry\.attempts: 0 must be a whole number in \[1, 1000\]"),
        ({"attempts": 2.5}, r"^retry\.attempts: 2\.5 must be a whole number"),
        ({"attempts": True}, r"^retry\.attempts: True must be a whole number"),
        ({"initial_backoff_s": 0}, r"^retry\.initial_backoff_s: 0 must be a number of seconds in \(0, 5\]"),
        ({"initial_backoff_s": 6}, r"^retry\.initial_backoff_s: 6 must be a number of seconds in \(0, 5\]"),
        ({"max_backoff_s": 61}, r"^retry\.max_backoff_s: 61 must be a number of seconds in \(0, 60\]"),
        ({"max_backoff_s": float("nan")}, r"^retry\.max_backoff_s: nan must be a number of seconds"),
    ],
)
def test_retry_policy_refuses_bad_values(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        RetryPolicy(**kwargs)


def test_retry_policy_backs_off_doubling_up_to_its_maximum() -> None:
    assert list(RetryPolicy(5, 0.1, 0.3).backoffs()) == [0.1, 0.2, 0.3, 0.3]
    assert list(RetryPolicy().backoffs()) == []
    assert RetryPolicy.retries(2) == RetryPolicy(attempts=3)
    with pytest.raises(InvalidArgument, match=r"^retries: -1 must be a whole number in \[0, 999\]"):
        RetryPolicy.retries(-1)
    with pytest.raises(InvalidArgument, match=r"^retry: expected a RetryPolicy, got int"):
        DrvsClient("127.0.0.1:1", retry=3)  # type: ignore[arg-type]


class _Seen(logging.Handler):
    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text
        self.seen = asyncio.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage():
            self.seen.set()


async def test_connect_retries_until_a_server_comes_up(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="drvs.robot")
    probe, address = await start_server()
    assert await probe.stop() == 0
    with pytest.raises(Unavailable, match=address):  # no retry: fails at once
        await DrvsClient.connect(address)

    retrying = _Seen("retrying the connection")
    logging.getLogger("drvs.robot").addHandler(retrying)
    policy = RetryPolicy(attempts=400, initial_backoff_s=0.05, max_backoff_s=0.2)
    connecting = asyncio.ensure_future(DrvsClient.connect(address, robot_id="r", retry=policy))
    server = None
    try:
        await asyncio.wait_for(retrying.seen.wait(), 10)  # it is retrying, with no server there
        assert not connecting.done()
        server, again = await start_server("--listen", address)
        assert again == address
        robot = await asyncio.wait_for(connecting, 30)
        try:
            assert await robot.cameras() == []
        finally:
            await robot.close()
    finally:
        logging.getLogger("drvs.robot").removeHandler(retrying)
        connecting.cancel()
        if server is not None:
            assert await server.stop() == 0


async def test_drvs_robot_retries_flag_waits_for_the_server() -> None:
    probe, address = await start_server()
    assert await probe.stop() == 0
    robot = await ManagedProcess.entry_point(
        "robot", "drvs-robot", "detect", "--server", address, "--filter", YELLOW, "--roi", "0,0,1,1",
        "--retries", "100", "--log-level", "INFO",
    ).start()  # fmt: skip
    server = None
    try:
        await robot.wait_for_line(r"retrying the connection", timeout=20)
        server, _ = await start_server("--listen", address)
        # It got its answer: nobody sees the region, so all of it went unseen (exit 3).
        assert await robot.wait(timeout=30) == 3, robot.output()
        assert "dispatched to no camera" in robot.output() and "1.0 m² of the region unseen" in robot.output()
    finally:
        await robot.stop()
        if server is not None:
            assert await server.stop() == 0


# --- subscriptions ---------------------------------------------------------------------------------------


async def test_an_unread_subscription_never_holds_back_another_request(office: Office) -> None:
    """One continuous request left unread well past its bound; another on the same camera (the same
    report stream) still gets every report, promptly; the unread one keeps its newest reports and
    counts the ones it dropped."""
    loop = asyncio.get_running_loop()
    async with DrvsClient.connect(office.address, robot_id="r", listen="127.0.0.1:0") as robot:
        unread = await robot.subscribe(YELLOW, CAM1_REGION, rate_hz=50, duration_s=6, max_queued=8)
        assert unread.camera_ids == ("cam1",)
        arrivals: list[float] = []
        async with robot.subscribe(YELLOW, CAM1_REGION, rate_hz=10, duration_s=3, timeout_s=3) as read:
            assert read.camera_ids == ("cam1",)
            async for _report in read:
                arrivals.append(loop.time())
        # The read request was not held back: its final report came, and no report waited long.
        assert read.result.complete and read.result.reports[-1].final, read.result.camera_errors
        assert len(arrivals) >= 20, len(arrivals)
        gaps = [b - a for a, b in itertools.pairwise(arrivals)]
        assert max(gaps) < 2.5, max(gaps)  # a held-back stream stalls for the camera's 5 s write timeout
        assert read.dropped == 0

        # The unread one, past its bound of 8 since about 0.2 s: the oldest were dropped and counted,
        # the newest kept, in order.
        assert unread.dropped > 50, unread.dropped
        kept: list[DetectionReport] = []
        async with unread:
            async for report in unread:
                kept.append(report)
                if len(kept) == 8:
                    break
        sequences = [r.sequence for r in kept]
        assert sequences == sorted(sequences) and len(set(sequences)) == 8
        assert sequences[0] >= unread.dropped, (sequences, unread.dropped)
        assert unread.closed  # leaving the block closed it


async def test_single_shot_results_keep_every_final_report(office: Office) -> None:
    """The bound applies to a continuous request's unread reports only: a single shot over two
    cameras with max_queued=1, read only after both have answered, still has both finals."""
    async with DrvsClient.connect(office.address, robot_id="r") as robot:
        async with robot.subscribe(YELLOW, BOTH_REGION, timeout_s=10, max_queued=1) as sub:
            assert sorted(sub.camera_ids) == ["cam1", "cam2"]
            continuous = await robot.detect(YELLOW, BOTH_REGION, rate_hz=10, duration_s=0.5, timeout_s=10)
            # Both cameras answered the single shot before the continuous request finished.
            assert continuous.complete
            result = await sub.collect()
        assert result.complete and sorted(r.camera_id for r in result.reports) == ["cam1", "cam2"]
        assert sub.dropped == 0 and result.dropped == 0
        assert sub.closed and not robot._subscriptions


async def test_subscribe_is_awaitable_and_a_context_manager_that_cancels(office: Office) -> None:
    async with DrvsClient.connect(office.address, robot_id="r") as robot:
        async with robot.subscribe(YELLOW, CAM1_REGION, rate_hz=10, duration_s=60) as sub:
            first = await anext(aiter(sub))
            assert first.camera_id == "cam1" and not first.final
        assert sub.closed and sub.request_id not in robot._subscriptions
        # The camera was told: it logs the cancelled request (it runs at DEBUG in the office).
        await office.cameras["cam1"].wait_for_line(rf"request {sub.request_id} cancel", timeout=10)
        old_form = await robot.subscribe(YELLOW, CAM1_REGION, timeout_s=10)
        assert (await old_form.collect()).complete


# --- errors ----------------------------------------------------------------------------------------------


async def test_errors_carry_their_code_and_the_failed_camera(refused_address: str) -> None:
    """A camera registered at an address where nothing listens: the server cannot reach it, and the
    result says so as a typed value whose exception carries .code and .camera_id."""
    server, address = await start_server()
    try:
        async with aio.insecure_channel(address) as channel:
            await registry_pb2_grpc.RegisterVisionServiceStub(channel).Register(
                register_message("ghost", address=refused_address),
                timeout=5,
            )
        async with DrvsClient.connect(address, robot_id="r") as robot:
            result = await robot.detect(YELLOW, (-1.0, 3.0, 1.0, 6.0), timeout_s=10)
            assert not result.complete
            error = result.camera_errors["ghost"]
            assert isinstance(error, CameraError)
            assert error.code == "UNAVAILABLE" and error.camera_id == "ghost" and error.message
            for report in result.reports:  # a report that carries the failure carries it typed
                if report.error:
                    assert report.camera_error == CameraError(report.error_code, report.error, "ghost")
            with pytest.raises(Unavailable) as caught:
                result.raise_for_errors()
            assert caught.value.code == "UNAVAILABLE" and caught.value.camera_id == "ghost"
            assert str(caught.value) == error.message

            # The server's own refusal: its status name, no camera.
            with pytest.raises(DrvsError) as refused:
                await robot.detect("model_nosuchmodel", (-1.0, 3.0, 1.0, 6.0), timeout_s=5)
            assert refused.value.code == type(refused.value).code != "UNKNOWN"
            assert refused.value.camera_id is None
    finally:
        assert await server.stop() == 0


def test_every_error_class_has_its_status_name() -> None:
    import grpc

    from drvs.wire import _grpc

    for code, cls in errors.BY_CODE.items():
        assert cls.code == code and grpc.StatusCode[code] == _grpc.status_of(cls("x"))
        made = errors.error_for(code, "why", camera_id="cam9")
        assert type(made) is cls and made.camera_id == "cam9" and str(made) == "why"
    unknown = errors.error_for("NO_SUCH_STATUS", "why")
    assert type(unknown) is DrvsError and unknown.code == "UNKNOWN" and unknown.camera_id is None


# --- documentation and the package ---------------------------------------------------------------------


def _public(module: Any) -> list[tuple[str, Any]]:
    names = getattr(module, "__all__", None) or [n for n in vars(module) if not n.startswith("_")]
    return [(n, getattr(module, n)) for n in names if callable(getattr(module, n))]


@pytest.mark.parametrize("module", [drvs.robot, errors, model], ids=lambda m: m.__name__)
def test_every_public_name_has_a_docstring(module: Any) -> None:
    for name, value in _public(module):
        if getattr(value, "__module__", "").split(".")[0] != "drvs":
            continue  # imported from elsewhere (shapely, typing ...)
        doc = value.__doc__ or ""
        # A dataclass without a docstring gets its signature as __doc__: that is not documentation.
        assert doc and not doc.startswith(f"{name}("), f"{module.__name__}.{name} has no docstring"


def test_help_of_the_client_reads_as_documentation() -> None:
    text = pydoc.plain(pydoc.render_doc(drvs.DrvsClient))
    for phrase in (
        "connect_timeout_s",  # connect
        "rpc_timeout_s",
        "seconds to wait, after the server's reply and beyond `duration_s`",  # timeout_s
        "max_queued",
        "RetryPolicy",
        "Unavailable",
        "`.code`",
        "Constructing one does no network work",
    ):
        assert phrase in text, phrase
    for method in ("connect", "subscribe", "detect", "cameras", "start", "close", "check_server"):
        assert getattr(drvs.DrvsClient, method).__doc__, method


def test_every_handle_is_an_async_context_manager() -> None:
    """`async with` works the same on each: what connect, subscribe and track return, and the
    Subscription and Track they open."""
    from drvs.robot import Connecting, Subscribing, Subscription, Track, Tracking

    for handle in (Connecting, Subscribing, Subscription, Tracking, Track):
        assert callable(getattr(handle, "__aenter__", None)) and callable(getattr(handle, "__aexit__", None)), handle


def test_import_drvs_is_light_and_re_exports_the_robot_api() -> None:
    code = (
        "import sys, drvs\n"
        "assert 'cv2' not in sys.modules and 'grpc' not in sys.modules, 'heavy import drvs'\n"
        "from drvs import DrvsClient, RetryPolicy, Detection, DetectionReport, DetectionResult, CameraError\n"
        "from drvs import DrvsError, Unavailable, InvalidArgument\n"
        "import drvs.robot, drvs.core.errors, drvs.core.model\n"
        "assert DrvsClient is drvs.robot.DrvsClient and Unavailable is drvs.core.errors.Unavailable\n"
        "from drvs import Security\n"
        "import drvs.wire.security\n"
        "assert Security is drvs.wire.security.Security is drvs.robot.Security\n"
        "assert 'cv2' not in sys.modules, 'the robot API imports cv2'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def _readme_robot_examples() -> list[str]:
    """The examples people copy: the README's five lines, then docs/robot-api.md's fuller and fused ones."""
    root = Path(__file__).parents[2]
    readme = (root / "README.md").read_text().split("## Use DRVS from robot code", 1)[1].split("\n## ", 1)[0]
    api = (root / "docs" / "robot-api.md").read_text().split("\n## Make a robot a vision source", 1)[0]
    return [code for text in (readme, api) for code in re.findall(r"```python\n(.*?)```", text, flags=re.S)]


async def test_the_readme_robot_examples_run_against_real_processes(office: Office) -> None:
    five_lines, fuller, fused = _readme_robot_examples()
    assert len([line for line in five_lines.splitlines() if line.strip()]) <= 8  # imports, def, run included
    for name, code in (("five-lines", five_lines), ("fuller", fuller), ("fused", fused)):
        proc = await ManagedProcess(
            name, [sys.executable, "-c", code.replace("drvs.example:50051", office.address)]
        ).start()
        try:
            assert await proc.wait(timeout=60) == 0, proc.output()
        finally:
            await proc.stop()
        output = proc.output()
        if name == "five-lines":
            # The yellow disc at (1.5, 3.0), the one in the box (0, 0, 5, 5), seen by cam1.
            (camera_id, x, y), *others = ast.literal_eval(output.strip().splitlines()[-1])
            assert not others and camera_id == "cam1" and math.dist((x, y), (1.5, 3.0)) < 0.03, output
        elif name == "fuller":
            assert "dropped unread: 0" in output and "cam1" in output, output
        else:
            # The same disc as one world object, then a track of it: 21 snapshots, one id throughout.
            lines = output.strip().splitlines()
            shot = re.fullmatch(r"1 \(([-\d.e]+), ([-\d.e]+)\) [\d.e-]+ \('cam1',\)", lines[0])
            assert shot and math.dist((float(shot[1]), float(shot[2])), (1.5, 3.0)) < 0.03, output
            tracked = [line.split(" ", 2) for line in lines[1:]]
            assert [int(n) for n, _, _ in tracked] == list(range(21)), output
            assert {track_id for _, track_id, _ in tracked} == {"1"}, output
