"""The camera registry: routing by field of view, leases on an injected clock, validation."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon, box

from drvs.core.errors import InvalidArgument, NotFound
from drvs.core.geometry import FieldOfView, Homography, box_region, homography_from_pose, polygon_region
from drvs.server.registry import Registry

SIZE = (640, 480)
TTL = 10.0
T0 = 1000.0


class Clock:
    """A settable clock: `now` is a mutable float the registry reads through a closure."""

    def __init__(self, start: float = T0) -> None:
        self.now = start

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def reader(self) -> Callable[[], float]:
        def read() -> float:
            return self.now

        return read


def camera_at(x: float, y: float = 0.0) -> Homography:
    """3 m up, looking along +y, 40° down: sees x-1.8..x+1.8 at y+1.5 widening to x±5.6 at y+10.1."""
    return homography_from_pose((x, y, 3.0), 90.0, 40.0, 60.0, SIZE)


def new_registry(clock: Clock) -> Registry:
    return Registry(lease_ttl_s=TTL, clock=clock.reader())


def register(
    reg: Registry, camera_id: str, x: float, y: float = 0.0, kinds: frozenset[str] = frozenset({"hsv"})
) -> None:
    reg.register(camera_id, "127.0.0.1:50051", camera_at(x, y), SIZE, kinds, 15.0)


def ids(reg: Registry, region: Polygon, kind: str | None = None) -> list[str]:
    return [e.camera_id for e in reg.cameras_seeing(region, kind)]


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def three(clock: Clock) -> Registry:
    """cam-a at x=0, cam-b at x=20, cam-c at x=40: fields of view far apart."""
    reg = new_registry(clock)
    register(reg, "cam-a", 0.0)
    register(reg, "cam-b", 20.0)
    register(reg, "cam-c", 40.0)
    return reg


def test_register_stores_the_field_of_view(three: Registry) -> None:
    assert len(three) == 3
    assert "cam-a" in three
    assert "cam-z" not in three
    entry = three.get("cam-b")
    assert entry.camera_id == "cam-b"
    assert entry.address == "127.0.0.1:50051"
    assert entry.detector_kinds == frozenset({"hsv"})
    assert entry.image_size == SIZE
    expected = FieldOfView.compute(camera_at(20.0), SIZE, 15.0).floor
    assert entry.field_of_view.equals(expected)
    assert [e.camera_id for e in three.cameras()] == ["cam-a", "cam-b", "cam-c"]


def test_cameras_seeing_returns_exactly_the_overlapping_ones(three: Registry) -> None:
    assert ids(three, box_region(-1.0, 3.0, 1.0, 5.0)) == ["cam-a"]
    assert ids(three, box_region(19.0, 3.0, 21.0, 5.0)) == ["cam-b"]
    assert ids(three, box_region(-1.0, 3.0, 21.0, 5.0)) == ["cam-a", "cam-b"]
    assert ids(three, box_region(-10.0, 0.0, 50.0, 20.0)) == ["cam-a", "cam-b", "cam-c"]
    # Between the cameras, behind them, and beyond their range: nobody.
    assert ids(three, box_region(9.0, 3.0, 11.0, 5.0)) == []
    assert ids(three, box_region(-1.0, -5.0, 41.0, 1.0)) == []
    assert ids(three, box_region(-1.0, 11.0, 41.0, 30.0)) == []
    # A polygon that crosses cam-c's field of view only.
    assert ids(three, polygon_region([(35.0, 2.0), (45.0, 2.0), (40.0, 4.0)])) == ["cam-c"]


def test_region_touching_only_an_edge_or_a_point_is_not_seen(three: Registry) -> None:
    fov = three.get("cam-a").field_of_view
    ring = list(fov.exterior.coords)[:-1]
    # The near edge of the field of view joins its two lowest vertices; a quadrilateral hanging below
    # it from exactly those vertices shares that edge and nothing else.
    (ax, ay), (bx, by) = sorted(ring, key=lambda p: p[1])[:2]
    below = Polygon([(ax, ay), (bx, by), (bx, by - 1.0), (ax, ay - 1.0)])
    assert below.is_valid
    assert below.intersects(fov)
    assert shapely.area(below.intersection(fov)) <= 1e-12
    assert ids(three, below) == []
    # Likewise along the slanted left edge, from the near-left to the far-left vertex.
    (lx0, ly0), (lx1, ly1) = sorted(ring, key=lambda p: p[0])[:2]
    beside = Polygon([(lx0, ly0), (lx1, ly1), (lx1 - 1.0, ly1), (lx0 - 1.0, ly0)])
    assert beside.is_valid
    assert beside.intersects(fov)
    assert ids(three, beside) == []
    # The far right corner is the field of view's rightmost point; a box whose corner is that vertex.
    corner = max(fov.exterior.coords, key=lambda p: p[0])
    touching = box(corner[0], corner[1], corner[0] + 1.0, corner[1] + 1.0)
    assert touching.intersects(fov)
    assert shapely.area(touching.intersection(fov)) == 0.0
    assert ids(three, touching) == []
    # The smallest real overlap is seen.
    y0 = fov.bounds[1]
    overlapping = box(-1.0, y0 - 1.0, 1.0, y0 + 0.01)
    assert ids(three, overlapping) == ["cam-a"]


def test_kind_filter(clock: Clock) -> None:
    reg = new_registry(clock)
    register(reg, "cam-hsv", 0.0, kinds=frozenset({"hsv"}))
    register(reg, "cam-both", 2.0, kinds=frozenset({"hsv", "aruco"}))
    region = box_region(-1.0, 3.0, 3.0, 5.0)
    assert ids(reg, region) == ["cam-both", "cam-hsv"]
    assert ids(reg, region, "hsv") == ["cam-both", "cam-hsv"]
    assert ids(reg, region, "aruco") == ["cam-both"]
    assert ids(reg, region, "yolo") == []


def test_lease_expiry(three: Registry, clock: Clock) -> None:
    region = box_region(-10.0, 0.0, 50.0, 20.0)
    assert three.remaining_s("cam-a") == TTL
    clock.advance(TTL - 0.001)
    assert ids(three, region) == ["cam-a", "cam-b", "cam-c"]
    assert three.expire() == []
    clock.advance(0.001)  # exactly at the end of the lease: expired
    assert ids(three, region) == []
    assert three.cameras() == []
    assert not three.is_live("cam-a")
    assert three.remaining_s("cam-a") == 0.0
    gone = three.expire()
    assert sorted(e.camera_id for e in gone) == ["cam-a", "cam-b", "cam-c"]
    assert len(three) == 0
    assert three.expire() == []
    with pytest.raises(NotFound, match=r"camera_id: 'cam-a'"):
        three.renew("cam-a")
    with pytest.raises(NotFound, match=r"camera_id: 'cam-a'"):
        three.get("cam-a")


def test_renew_after_expiry_raises_and_drops_the_camera(three: Registry, clock: Clock) -> None:
    clock.advance(TTL + 1.0)
    with pytest.raises(NotFound, match=r"camera_id: 'cam-b'.*expired"):
        three.renew("cam-b")
    assert "cam-b" not in three
    assert len(three) == 2


def test_renew_extends_the_lease(three: Registry, clock: Clock) -> None:
    region = box_region(-1.0, 3.0, 1.0, 5.0)
    clock.advance(8.0)
    entry = three.renew("cam-a")
    assert entry is three.get("cam-a")
    assert three.remaining_s("cam-a") == TTL
    clock.advance(5.0)  # 13 s after registering: cam-b and cam-c are gone, cam-a lives until 18 s
    assert ids(three, region) == ["cam-a"]
    assert ids(three, box_region(-10.0, 0.0, 50.0, 20.0)) == ["cam-a"]
    assert [e.camera_id for e in three.expire()] == ["cam-b", "cam-c"]
    clock.advance(5.0)
    assert ids(three, region) == []
    assert [e.camera_id for e in three.expire()] == ["cam-a"]


def test_renew_unknown_camera(three: Registry) -> None:
    with pytest.raises(NotFound, match=r"camera_id: 'nope' is not registered"):
        three.renew("nope")


def test_re_register_replaces_the_entry(three: Registry, clock: Clock) -> None:
    old_region = box_region(-1.0, 3.0, 1.0, 5.0)
    new_region = box_region(99.0, 3.0, 101.0, 5.0)
    assert ids(three, old_region) == ["cam-a"]
    clock.advance(9.0)
    register(three, "cam-a", 100.0)
    assert len(three) == 3
    assert ids(three, old_region) == []
    assert ids(three, new_region) == ["cam-a"]
    # Re-registering renews the lease.
    assert three.remaining_s("cam-a") == TTL
    clock.advance(5.0)
    assert ids(three, new_region) == ["cam-a"]


def test_remove(three: Registry) -> None:
    removed = three.remove("cam-b")
    assert removed.camera_id == "cam-b"
    assert len(three) == 2
    assert ids(three, box_region(19.0, 3.0, 21.0, 5.0)) == []
    with pytest.raises(NotFound, match=r"camera_id: 'cam-b' is not registered"):
        three.remove("cam-b")
    with pytest.raises(NotFound, match=r"camera_id: 'unknown' is not registered"):
        three.remove("unknown")


def test_empty_registry_sees_nothing(clock: Clock) -> None:
    reg = new_registry(clock)
    assert ids(reg, box_region(-10.0, -10.0, 10.0, 10.0)) == []
    assert reg.expire() == []


def test_lease_ttl_must_be_positive(clock: Clock) -> None:
    with pytest.raises(ValueError, match=r"lease_ttl_s"):
        Registry(lease_ttl_s=0.0, clock=clock.reader())


def _pitched_up() -> Homography:
    return homography_from_pose((0.0, 0.0, 3.0), 90.0, -30.0, 60.0, SIZE)


def _rank_deficient() -> Homography:
    # Built directly (as a bug elsewhere could): maps every pixel onto the line x = y.
    return Homography(np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.01, 1.0]]))


@pytest.mark.parametrize(
    ("camera_id", "address", "homography", "size", "kinds", "max_range", "message"),
    [
        ("cam a", "127.0.0.1:1", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^camera_id: "),
        ("cam/a", "127.0.0.1:1", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^camera_id: "),
        ("", "127.0.0.1:1", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^camera_id: empty"),
        ("cam\u00e9ra", "127.0.0.1:1", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^camera_id: "),
        ("c" * 129, "127.0.0.1:1", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^camera_id: longer than 128"),
        ("cam-a", "127.0.0.1", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^address: "),
        ("cam-a", "127.0.0.1:0", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^address: port 0"),
        ("cam-a", "127.0.0.1:70000", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^address: port 70000"),
        ("cam-a", "", camera_at(0.0), SIZE, {"hsv"}, 15.0, r"^address: empty"),
        ("cam-a", "127.0.0.1:1", camera_at(0.0), SIZE, set(), 15.0, r"^detector_kinds: empty"),
        ("cam-a", "127.0.0.1:1", camera_at(0.0), SIZE, {"h s v"}, 15.0, r"^detector_kinds: "),
        ("cam-a", "127.0.0.1:1", _pitched_up(), SIZE, {"hsv"}, 15.0, r"^field_of_view: .*sees no floor"),
        ("cam-a", "127.0.0.1:1", _rank_deficient(), SIZE, {"hsv"}, 15.0, r"^field_of_view: .*sees no floor"),
        ("cam-a", "127.0.0.1:1", camera_at(0.0), (0, 480), {"hsv"}, 15.0, r"^field_of_view: image size"),
        ("cam-a", "127.0.0.1:1", camera_at(0.0), SIZE, {"hsv"}, -1.0, r"^field_of_view: max_range_m"),
    ],
)
def test_invalid_registration_changes_nothing(
    three: Registry,
    clock: Clock,
    camera_id: str,
    address: str,
    homography: Homography,
    size: tuple[int, int],
    kinds: set[str],
    max_range: float,
    message: str,
) -> None:
    clock.advance(3.0)
    everywhere = box_region(-10.0, 0.0, 50.0, 20.0)
    before_entries = {cid: three.get(cid) for cid in ("cam-a", "cam-b", "cam-c")}
    before_remaining = {cid: three.remaining_s(cid) for cid in before_entries}
    before_seen = ids(three, everywhere)
    with pytest.raises(InvalidArgument, match=message):
        three.register(camera_id, address, homography, size, kinds, max_range)
    assert len(three) == 3
    assert ids(three, everywhere) == before_seen == ["cam-a", "cam-b", "cam-c"]
    assert ids(three, box_region(-1.0, 3.0, 1.0, 5.0)) == ["cam-a"]
    for cid, entry in before_entries.items():
        assert three.get(cid) is entry
        assert three.remaining_s(cid) == before_remaining[cid]


@pytest.mark.slow
def test_many_cameras_route_to_the_few_near_the_region(clock: Clock) -> None:
    # 50 x 40 cameras, 10 m apart. Neighbours along x overlap only near their far edges (y + 9..10);
    # rows 10 m apart along y never overlap (each sees y + 1.5 .. y + 10.1).
    reg = new_registry(clock)
    for i in range(50):
        for j in range(40):
            register(reg, f"cam-{i:02d}-{j:02d}", 10.0 * i, 10.0 * j)
    assert len(reg) == 2000
    # In the middle of one camera's view.
    assert ids(reg, box_region(99.75, 104.75, 100.25, 105.25)) == ["cam-10-10"]
    # Where two neighbours' far corners overlap.
    assert ids(reg, box_region(104.9, 109.7, 105.1, 109.9)) == ["cam-10-10", "cam-11-10"]
    # In the gap between two neighbours' near edges, and between two rows.
    assert ids(reg, box_region(104.9, 101.9, 105.1, 102.1)) == []
    assert ids(reg, box_region(99.0, 110.5, 101.0, 111.2)) == []
    # A region spanning two rows of one column.
    assert ids(reg, box_region(249.5, 254.0, 250.5, 264.0)) == ["cam-25-25", "cam-25-26"]
    # Against a brute-force check over every camera, for a few boxes spread over the grid.
    rng = np.random.default_rng(7)
    for _ in range(20):
        x, y = rng.uniform(0.0, 490.0), rng.uniform(0.0, 390.0)
        region = box_region(x, y, x + 1.0, y + 1.0)
        expected = sorted(e.camera_id for e in reg.cameras() if e.field_of_view.intersection(region).area > 1e-9)
        got = ids(reg, region)
        assert got == expected
        assert len(got) <= 4


def test_a_region_asked_about_again_is_routed_afresh_after_every_change(clock: Clock) -> None:
    reg = new_registry(clock)
    register(reg, "a", 0.0)
    region = box(-1.0, 3.0, 1.0, 4.0)  # the same object each time, as region_from_pb hands out
    assert ids(reg, region) == ["a"]
    register(reg, "b", 0.5)
    assert ids(reg, region) == ["a", "b"]  # a new camera is seen at once
    register(reg, "b", 50.0)
    assert ids(reg, region) == ["a"]  # and a moved one is not
    reg.remove("a")
    assert ids(reg, region) == []
    register(reg, "c", 0.0, kinds=frozenset({"aruco"}))
    assert ids(reg, region, "hsv") == [] and ids(reg, region, "aruco") == ["c"]
    clock.advance(TTL / 2)
    register(reg, "d", 0.0)
    clock.advance(TTL / 2)  # c's lease has run out, d's has not: no registration change in between
    assert ids(reg, region) == ["d"]
    # Equal regions in other objects route the same.
    assert ids(reg, box(-1.0, 3.0, 1.0, 4.0)) == ["d"]


def test_routing_memory_is_bounded(clock: Clock) -> None:
    from drvs.server import registry

    reg = new_registry(clock)
    register(reg, "a", 0.0)
    regions = [box(-1.0 + i * 1e-6, 3.0, 1.0, 4.0) for i in range(registry.ROUTE_CACHE_SIZE + 50)]
    assert all(ids(reg, r) == ["a"] for r in regions)
    assert len(reg._routes) == registry.ROUTE_CACHE_SIZE


def brute_force(reg: Registry, region: Polygon, kind: str | None, frame: str | None) -> list[str]:
    """Every live camera whose field of view meets `region` with positive area, one by one."""
    return sorted(
        e.camera_id
        for e in reg.cameras()
        if e.field_of_view.intersection(region).area > 0
        and (kind is None or kind in e.detector_kinds)
        and (frame is None or e.frame == frame)
    )


def random_camera(rng: np.random.Generator) -> tuple[Homography, float]:
    """A camera anywhere in a 200 m square, any heading and tilt, 2 to 60 m of range: fields of
    view from a few metres to a hundred wide, so the index's levels all fill."""
    x, y = rng.uniform(0.0, 200.0, size=2)
    h = homography_from_pose(
        (x, y, rng.uniform(2.0, 8.0)), rng.uniform(0.0, 360.0), rng.uniform(25.0, 70.0), 60.0, SIZE
    )
    return h, float(rng.uniform(2.0, 60.0))


def random_region(rng: np.random.Generator) -> Polygon:
    """A box from 0.1 m to the whole site (both ways of reading the index), or a triangle."""
    x, y = rng.uniform(-20.0, 220.0, size=2)
    side = float(10.0 ** rng.uniform(-1.0, 2.5))
    if rng.random() < 0.2:
        return Polygon([(x, y), (x + side, y + 0.3 * side), (x + 0.2 * side, y + side)])
    return box(x, y, x + side, y + side * rng.uniform(0.2, 1.0))


def test_lookups_equal_a_brute_force_check_through_adds_removes_replacements_and_expiries(clock: Clock) -> None:
    rng = np.random.default_rng(27)
    reg = new_registry(clock)
    frames = ("map", "building-a/floor-2")
    kinds = (frozenset({"hsv"}), frozenset({"aruco"}), frozenset({"hsv", "aruco"}))
    live: list[str] = []
    for step in range(400):
        op = rng.random()
        if op < 0.6 or len(live) < 10:  # a new camera, or one replaced (moved, other kinds or frame)
            camera_id = f"c{step}" if op < 0.4 or not live else live[int(rng.integers(len(live)))]
            h, max_range = random_camera(rng)
            kind = kinds[int(rng.integers(3))]
            reg.register(camera_id, "127.0.0.1:9", h, SIZE, kind, max_range, frame=frames[int(rng.integers(2))])
            if camera_id not in live:
                live.append(camera_id)
        elif op < 0.8:
            reg.remove(live.pop(int(rng.integers(len(live)))))
        else:  # time passes: the oldest leases lapse, and expire() drops them
            clock.advance(float(rng.uniform(0.0, TTL / 20)))
            if rng.random() < 0.5:
                gone = {e.camera_id for e in reg.expire()}
                live = [c for c in live if c not in gone]
        for _ in range(3):
            region = random_region(rng)
            kind_asked = (None, "hsv", "aruco")[int(rng.integers(3))]
            frame_asked = (None, *frames)[int(rng.integers(3))]
            got = [e.camera_id for e in reg.cameras_seeing(region, kind_asked, frame_asked)]
            assert got == brute_force(reg, region, kind_asked, frame_asked), (step, region.wkt)
    assert len(reg) > 20  # the walk kept a real population


def test_frames_are_indexed_apart(clock: Clock) -> None:
    reg = new_registry(clock)
    for camera_id, frame in (("ground", "map"), ("upstairs", "building-a/floor-2")):
        reg.register(camera_id, "127.0.0.1:9", camera_at(0.0), SIZE, {"hsv"}, 15.0, frame=frame)
    region = box(-1.0, 3.0, 1.0, 4.0)
    assert ids(reg, region) == ["ground"]  # the default frame
    assert [e.camera_id for e in reg.cameras_seeing(region, frame="building-a/floor-2")] == ["upstairs"]
    assert [e.camera_id for e in reg.cameras_seeing(region, frame=None)] == ["ground", "upstairs"]
    assert reg.cameras_seeing(region, frame="building-b") == []
    # Moving a camera to another floor moves it in the index.
    reg.register("ground", "127.0.0.1:9", camera_at(0.0), SIZE, {"hsv"}, 15.0, frame="building-b")
    assert ids(reg, region) == []
    assert [e.camera_id for e in reg.cameras_seeing(region, frame="building-b")] == ["ground"]


def test_a_large_region_and_a_wide_view_are_found_every_way(clock: Clock) -> None:
    """A region over more cells than SCAN_MIN_CELLS that hold cameras (every camera's bounds tested
    at once), one over fewer (the cells probed), and a view many of the finest cells wide."""
    from drvs.server import registry

    reg = new_registry(clock)
    for i in range(100):
        register(reg, f"near-{i:03d}", 10.0 * (i % 10), 10.0 * (i // 10))
    high = homography_from_pose((500.0, 500.0, 8.0), 90.0, 25.0, 80.0, SIZE)  # about 80 m x 60 m of floor
    reg.register("wide", "127.0.0.1:9", high, SIZE, {"hsv"}, 60.0)
    width = reg.get("wide").field_of_view.bounds
    assert width[2] - width[0] > 4 * registry.STATIC_CELL_M
    assert len(reg) > registry.SCAN_MIN_CELLS
    everything = box(-50.0, -50.0, 1000.0, 1000.0)
    assert ids(reg, everything) == brute_force(reg, everything, None, "map") and len(ids(reg, everything)) == 101
    some = box(15.0, 15.0, 45.0, 45.0)
    assert ((45 - 15) / registry.STATIC_CELL_M + 2) ** 2 < registry.SCAN_MIN_CELLS
    assert ids(reg, some) == brute_force(reg, some, None, "map") and len(ids(reg, some)) > 10
    # Just inside the wide view's far edge, many cells from the cell it sits in.
    far = box(width[0] + 0.4 * (width[2] - width[0]), width[3] - 3.0, width[0] + 0.6 * (width[2] - width[0]), width[3])
    assert ids(reg, far) == brute_force(reg, far, None, "map") == ["wide"]
    reg.remove("wide")
    assert ids(reg, far) == [] and len(ids(reg, everything)) == 100


def test_changes_update_the_index_in_place_and_pose_updates_never_touch_it(clock: Clock) -> None:
    from drvs.core.mobile import Mount
    from drvs.core.model import Pose2

    reg = Registry(lease_ttl_s=TTL, clock=clock.reader(), min_pose_interval_s=0.0)
    index = reg._tree
    register(reg, "fixed", 0.0)
    assert index.changes == 1 and len(index) == 1
    register(reg, "fixed", 0.0)  # a re-registration replaces the entry: out and in again
    assert index.changes == 3 and len(index) == 1
    mount = Mount(0.1, 0.0, 0.8, 0.0, 30.0, hfov_deg=70.0)
    reg.register("scout", "127.0.0.1:9", mount.base_homography(SIZE), SIZE, {"hsv"}, 6.0, mobile=True)
    region = box(-1.0, 3.0, 1.0, 4.0)
    assert ids(reg, region) == ["fixed"]
    for k in range(20):
        clock.advance(0.01)
        reg.update_pose("scout", Pose2(-4.0 + 0.2 * k, 3.5, 0.0))
        sees = reg.get("scout").field_of_view.intersection(region).area > 0
        assert ids(reg, region) == (["fixed", "scout"] if sees else ["fixed"])
    assert index.changes == 3 and len(index) == 1 and reg._tree is index
    # A fixed camera registered again as a mobile one leaves the index; a mobile one made fixed enters.
    reg.register("fixed", "127.0.0.1:9", mount.base_homography(SIZE), SIZE, {"hsv"}, 6.0, mobile=True)
    assert len(index) == 0 and "fixed" not in ids(reg, region)
    register(reg, "scout", 0.0)
    assert len(index) == 1 and ids(reg, region) == ["scout"]
    clock.advance(TTL)
    assert [e.camera_id for e in reg.expire()] == ["fixed", "scout"] and len(index) == 0
