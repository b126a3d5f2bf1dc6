"""Shared fixtures: a recorded two-camera floor, and DRVS roles started as real processes.
The constants and builders they use live in tests/helpers.py."""

from __future__ import annotations

from collections.abc import AsyncIterator, Generator, Iterator
from typing import TYPE_CHECKING

import pytest
import pytest_asyncio

from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import running

from .helpers import CAMERA_POSES, Office, once_per_run, record_floor, start_office, stop_office

if TYPE_CHECKING:
    from .live.office_view import OfficeRun


@pytest.fixture(autouse=True)
def _no_process_outlives_its_test(request: pytest.FixtureRequest) -> Iterator[None]:
    """Every process a test started (drvs.tools.launch) is stopped when the test ends, also when it fails
    or times out: this runs after the test's own fixtures have stopped theirs, SIGKILLs whatever is
    left, and fails a test that passed while leaving processes behind."""
    before = running()
    yield
    left = running() - before
    for proc in left:
        proc.kill()
    if left:
        names = ", ".join(sorted(f"{p.name} (pid {p.pid})" for p in left))
        report = getattr(request.node, "rep_call", None)
        if report is None or report.passed:
            pytest.fail(f"processes left running after the test (now killed): {names}")


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """Keep each phase's report on the test item, so fixtures can tell whether the test failed."""
    report = yield
    setattr(item, f"rep_{report.when}", report)
    return report


@pytest.fixture(scope="session")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, RecordedCamera]:
    """Two cameras' video files of the same floor, with their homography files."""
    return record_floor(tmp_path_factory.mktemp("floor"))


@pytest_asyncio.fixture
async def office(request: pytest.FixtureRequest, recorded: dict[str, RecordedCamera]) -> AsyncIterator[Office]:
    """drvs-server and two drvs-camera processes, lease 1.5 s; all reaped afterwards, also when the
    test fails. `@pytest.mark.office_cameras("cam1")` starts only cam1, `office_cameras()` the server
    alone: a test that needs only an address or one camera starts no more than that."""
    marker = request.node.get_closest_marker("office_cameras")
    cameras = tuple(CAMERA_POSES) if marker is None else tuple(marker.args)
    o = await start_office(recorded, lease_ttl=1.5, cameras=cameras)
    try:
        yield o
    finally:
        await stop_office(o)


@pytest_asyncio.fixture(scope="session", loop_scope="session")
async def default_office(tmp_path_factory: pytest.TempPathFactory) -> OfficeRun:
    """One run of the office as it ships, watched live (tests/live/office_view.py), made once per
    test run (once_per_run: one worker makes it, another that asks reads it). Its processes are all
    stopped before the first test that asks for it starts."""
    from .live.office_view import OfficeRun, run_default_office

    return OfficeRun(**await once_per_run(tmp_path_factory, "default-office", run_default_office))
