"""drvs-bench service's churn figures: registry lookups while cameras come and go, against the
floor that rebuilds its STRtree whole after each change. Each run is a fresh interpreter
(`python -m drvs_bench.service_churn churn MODE CAMERAS SECONDS SEED`), so its peak RSS is its own.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import shapely
from shapely import STRtree
from shapely.geometry import Polygon, box

from drvs.core.geometry import FieldOfView
from drvs.server.registry import CameraEntry, Registry

from .common import (
    peak_rss_bytes,
)
from .helpers import percentile
from .stats import WorkMismatch, interleaved, publish, verdict

#: Issue 27 item 8: the registry under churn. Cameras, registration changes a second, wall seconds of
#: churn per run; --quick and full.
CHURN_CAMERAS, CHURN_CAMERAS_QUICK = 100_000, 2_000
CHURN_RATE = 100
CHURN_SECONDS, CHURN_SECONDS_QUICK = 8.0, 1.0
#: Smaller registries, one round each in the full run: where the whole rebuild stops being cheap.
CHURN_SWEEP = (1_000, 10_000)
CHURN_TARGET_P99_US = 1000.0
#: Leases of the cameras that come and go, in ticks of the churn's clock (one tick per change).
CHURN_LEASE_TICKS = 150
CHURN_SPACING_M = 10.0


class RebuildWhole:
    """The floor: the registry's index as it was before issue 27, kept here to compare with: an
    STRtree over every fixed camera, rebuilt whole on the first lookup after any change."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._entries: dict[str, CameraEntry] = {}
        self._expires: dict[str, float] = {}
        self._tree: STRtree | None = None
        self._tree_entries: list[CameraEntry] = []
        self._fovs: np.ndarray = np.array([], dtype=object)

    def store(self, entry: CameraEntry, lease_s: float) -> None:
        self._entries[entry.camera_id] = entry
        self._expires[entry.camera_id] = self._clock() + lease_s
        self._tree = None

    def hold(self, camera_id: str) -> None:
        self._expires[camera_id] = math.inf

    def expire(self) -> list[str]:
        now = self._clock()
        gone = [cid for cid, t in self._expires.items() if t <= now]
        for cid in gone:
            del self._entries[cid], self._expires[cid]
        if gone:
            self._tree = None
        return gone

    def cameras_seeing(self, region: Polygon, kind: str) -> list[CameraEntry]:
        if self._tree is None:
            self._tree_entries = list(self._entries.values())
            self._fovs = np.array([e.field_of_view for e in self._tree_entries], dtype=object)
            self._tree = STRtree(self._fovs)
        candidates = np.sort(self._tree.query(region, predicate="intersects"))
        hits = shapely.relate_pattern(self._fovs[candidates], region, "T********")
        now = self._clock()
        found = [
            self._tree_entries[i]
            for i, hit in zip(candidates, hits, strict=True)
            if hit
            and self._expires[self._tree_entries[i].camera_id] > now
            and kind in self._tree_entries[i].detector_kinds
        ]
        return sorted(found, key=lambda e: e.camera_id)


def churn_run(mode: str, cameras: int, seconds: float, seed: int) -> dict[str, Any]:
    """One registry (`index`: drvs.server.registry.Registry; `rebuild_whole`: the floor) of `cameras` fixed
    cameras on a square grid, then `seconds` of lookups back to back with registration changes due
    at CHURN_RATE a second between them: in turn a new camera, a camera registering again (moved up
    to 1 m) and a lapsed lease (the new cameras' leases lapse CHURN_LEASE_TICKS changes later;
    expire() runs each CHURN_RATE changes, as the server's once a second). Run in a process of its own,
    so that its peak RSS is its registry's."""
    from drvs.core.geometry import Homography, homography_from_pose

    tick = 0.0
    clock = lambda: tick  # noqa: E731  (the churn's clock: one tick per change)
    side = math.ceil(math.sqrt(cameras))
    size = (640, 480)

    def pose(x: float, y: float) -> Homography:
        return homography_from_pose((x, y, 3.0), 90.0, 40.0, 60.0, size)

    # The cameras' fields of view and homographies: one computed, the rest moved along the grid.
    h0 = pose(0.0, 0.0)
    ring = shapely.get_coordinates(FieldOfView.compute(h0, size, 6.0).floor)
    xy = np.stack([np.arange(cameras) % side, np.arange(cameras) // side], axis=1) * CHURN_SPACING_M
    fovs = shapely.polygons(ring[None, :, :] + xy[:, None, :])
    checker = Registry(lease_ttl_s=CHURN_LEASE_TICKS, clock=clock)
    registry = Registry(lease_ttl_s=CHURN_LEASE_TICKS, clock=clock)
    floor = RebuildWhole(clock)
    kinds = frozenset({"hsv"})
    for i in range(cameras):
        shift = np.array([[1.0, 0.0, xy[i, 0]], [0.0, 1.0, xy[i, 1]], [0.0, 0.0, 1.0]]) @ h0.matrix
        h = Homography(shift / np.max(np.abs(shift)))
        entry = CameraEntry(f"c{i}", "127.0.0.1:9", fovs[i], kinds, h, size)
        if mode == "index":
            registry.store(entry)
            registry.hold(entry.camera_id)
        else:
            floor.store(entry, math.inf)
    rng = np.random.default_rng(seed)
    lookup_us: list[float] = []
    register_us: list[float] = []
    expire_us: list[float] = []
    empty = changes = expired = 0

    def register(camera_id: str, x: float, y: float) -> None:
        t0 = time.perf_counter()
        if mode == "index":
            registry.register(camera_id, "127.0.0.1:9", pose(x, y), size, kinds, 6.0)
        else:
            entry, _ = checker.check(camera_id, "127.0.0.1:9", pose(x, y), size, kinds, 6.0)
            floor.store(entry, CHURN_LEASE_TICKS)
        register_us.append((time.perf_counter() - t0) * 1e6)

    def change(k: int) -> None:
        nonlocal expired
        if k % 3 == 0:  # a new camera, somewhere on the grid
            register(f"new{k}", *(rng.uniform(0.0, side * CHURN_SPACING_M, size=2)))
        elif k % 3 == 1:  # a camera registers again, moved a little (its lease is kept elsewhere)
            i = int(rng.integers(cameras))
            register(f"c{i}", *(xy[i] + rng.uniform(-1.0, 1.0, size=2)))
            (registry if mode == "index" else floor).hold(f"c{i}")
        if k % CHURN_RATE == CHURN_RATE - 1:  # the server's expiry sweep, once a second
            t0 = time.perf_counter()
            expired += len(registry.expire() if mode == "index" else floor.expire())
            expire_us.append((time.perf_counter() - t0) * 1e6)

    def lookup() -> None:
        nonlocal empty
        x, y = xy[int(rng.integers(cameras))]
        region = box(x - 0.5, y + 3.0, x + 0.5, y + 4.0)  # a new region object each time
        t0 = time.perf_counter()
        found = registry.cameras_seeing(region, "hsv") if mode == "index" else floor.cameras_seeing(region, "hsv")
        lookup_us.append((time.perf_counter() - t0) * 1e6)
        empty += not found

    # Leases already running, so that they lapse from the first second on; one lookup builds the
    # floor's tree before the clock starts.
    for k in range(-CHURN_LEASE_TICKS, 0):
        tick = float(k)
        if k % 3 == 0:
            change(k)
    tick = 0.0
    lookup()
    lookup_us.clear()
    register_us.clear()
    expired = 0
    start = time.perf_counter()
    while (now := time.perf_counter() - start) < seconds:
        if now * CHURN_RATE >= changes:
            tick = float(changes)
            change(changes)
            changes += 1
        else:
            lookup()
    wall = time.perf_counter() - start
    while changes < seconds * CHURN_RATE:  # the changes that fell due during the last lookup
        tick = float(changes)
        change(changes)
        changes += 1
    return {
        "mode": mode,
        "cameras": cameras,
        "lookups": len(lookup_us),
        "lookups_empty": empty,
        "changes": changes,
        "expired": expired,
        "wall_s": wall,
        "lookup_p50_us": percentile(lookup_us, 50),
        "lookup_p99_us": percentile(lookup_us, 99),
        "lookup_max_us": max(lookup_us),
        "register_us": statistics.median(register_us),
        "expire_us": statistics.median(expire_us) if expire_us else 0.0,
        "peak_rss_mb": peak_rss_bytes(os.getpid()) / 2**20,
    }


def churn_child(mode: str, cameras: int, seconds: float, seed: int) -> dict[str, Any]:
    """churn_run in a fresh interpreter: its peak RSS is that registry's alone."""
    args = [sys.executable, "-m", "drvs_bench.service_churn", "churn", mode, str(cameras), str(seconds), str(seed)]
    done = subprocess.run(args, capture_output=True, text=True, timeout=900, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"churn {mode} {cameras}: exit {done.returncode}: {done.stderr[-2000:]}")
    run = dict(json.loads(done.stdout.strip().splitlines()[-1]))
    # Every change made, at the rate asked for; lookups done, and each found its camera.
    if not (run["changes"] == math.ceil(seconds * CHURN_RATE) and run["lookups"] > 0 and run["lookups_empty"] == 0):
        raise WorkMismatch(f"churn {mode} at {cameras} cameras did not do its work: {run}")
    return run


def measure_churn(quick: bool, out: dict[str, Any], n_rounds: int) -> None:
    """Lookups while cameras come and go at CHURN_RATE changes a second: the registry against the floor
    that rebuilds its STRtree whole after each change, interleaved round by round."""
    cameras = CHURN_CAMERAS_QUICK if quick else CHURN_CAMERAS
    seconds = CHURN_SECONDS_QUICK if quick else CHURN_SECONDS
    per_round: list[dict[str, dict[str, Any]]] = [{} for _ in range(n_rounds)]
    for r, mode in interleaved(("index", "rebuild_whole"), n_rounds):
        per_round[r][mode] = churn_child(mode, cameras, seconds, seed=r)
    churn: dict[str, Any] = {"cameras": cameras, "changes_per_s": CHURN_RATE, "seconds_per_run": seconds}
    for key in ("lookup_p50_us", "lookup_p99_us", "lookup_max_us", "register_us", "expire_us", "peak_rss_mb"):
        publish(churn, key, [round(f["index"][key], 1) for f in per_round])
        publish(churn, f"rebuild_whole_{key.removeprefix('lookup_')}", [
            round(f["rebuild_whole"][key], 1) for f in per_round
        ])  # fmt: skip
    churn["lookups_per_run"] = [f["index"]["lookups"] for f in per_round]
    churn["rebuild_whole_lookups_per_run"] = [f["rebuild_whole"]["lookups"] for f in per_round]
    churn["expired_per_run"] = [f["index"]["expired"] for f in per_round]
    churn["target_p99_us"] = CHURN_TARGET_P99_US
    churn["verdict"] = verdict(churn["lookup_p99_us_runs"], CHURN_TARGET_P99_US, higher_is_better=False)
    churn["met"] = churn["verdict"] == "met"
    if not quick:  # where the crossover is: smaller registries, one round each
        churn["by_cameras"] = {
            str(n): {
                mode: {k: round(run[k], 1) for k in ("lookup_p50_us", "lookup_p99_us", "lookup_max_us")}
                for mode in ("index", "rebuild_whole")
                for run in (churn_child(mode, n, CHURN_SECONDS_QUICK * 2, seed=0),)
            }
            for n in CHURN_SWEEP
        }
    churn["definition"] = (
        f"{cameras} fixed cameras 10 m apart on a square grid in one process (drvs.server.registry.Registry, no "
        f"server); for {seconds:g} s, lookups of a new 1 m box in front of a random camera back to back, "
        f"with {CHURN_RATE} registration changes a second due between them: new cameras, cameras registering "
        "again (moved up to 1 m, a real register() with its field of view computed) and the new cameras' "
        "leases lapsing (expire() once a second), a third each. lookup_*: cameras_seeing alone; register_us: "
        "register() (the floor: the same checks, then its store); peak_rss_mb: the process's VmHWM. "
        "rebuild_whole_*: the same run on the floor, an STRtree over every camera rebuilt whole on the "
        "first lookup after a change (the registry before issue 27). Modes interleaved, each run in a "
        "fresh process; median, spread and every round."
    )
    out["churn"] = churn


def main(argv: list[str]) -> int:
    """`python -m drvs_bench.service_churn churn MODE CAMERAS SECONDS SEED`: one churn run, its JSON last."""
    if len(argv) != 5 or argv[0] != "churn":
        print(
            "usage: python -m drvs_bench.service_churn churn index|rebuild_whole CAMERAS SECONDS SEED", file=sys.stderr
        )
        return 2
    print(json.dumps(churn_run(argv[1], int(argv[2]), float(argv[3]), int(argv[4]))), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
