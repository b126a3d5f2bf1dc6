"""Fusion: one world object per physical object, from the detections of several cameras.

Pure logic (no role, no I/O): the server calls `fuse` on the reports of one request (a single shot)
or of one period (a continuous request, then `drvs.server.tracking.Tracker`). docs/fusion.md explains the
model; in short:

- Precision. A camera's detector places an object's centroid to about `pixel_sigma` pixels; on the
  floor that is `pixel_sigma * GSD` metres, where the ground sampling distance (GSD) is the floor
  length one image pixel covers at that spot (`ground_sampling_distance`, from the camera's
  image->floor homography). A camera far from a spot, or looking at it at a grazing angle, has a
  larger GSD there and counts less.
- Grouping. Only detections of one type are merged: markers by marker id, everything else by
  label (within one request all detections come from one filter_def). Markers of one id merge
  whatever their distance (the id says it is the same marker). Other detections are candidate
  pairs when their floor outlines overlap (a share of the smaller one, `OVERLAP_FRACTION`) or when
  their centroids are within a gate: 3 sigma of the two cameras' combined precision plus an
  allowance for the object's size (`SIZE_ALLOWANCE`), because two cameras see a raised object's
  sides and top from different directions and the floor projection of what each sees is displaced
  away from it. Cameras are taken one at a time (sorted by id) and each camera's detections are
  assigned to the groups built so far with `scipy.optimize.linear_sum_assignment` (the optimal
  one-to-one assignment minimising gated, normalised distance), so two detections of one camera
  never share a group. A detection left unassigned starts a group of its own.
- Fused values. Centroid: the 1/sigma^2-weighted mean of the members' centroids; uncertainty_m:
  the fused sigma, 1/sqrt(sum 1/sigma_i^2), smaller than any member's. Outline: the UNION of the
  members' outlines, because a path planner must not drive into any part that any camera saw
  (the intersection would be tighter for a tall object, but it loses real floor area whenever the
  cameras' calibrations disagree by a few centimetres). Bounds: the outline's bounds, or without
  outlines (a request with omit_outlines) the union of the members' bounds. area_m2: the fused
  outline's area (without outlines: the largest member's). score: the best member's. last_seen:
  the newest capture time. camera_ids: sorted. marker_heading_deg: the members' headings averaged
  on the circle with the same weights. track_id: 1, 2, ... by x, then y, of the fused centroid.
- A camera that saw only part of an object (at its image's edge) has its sigma widened by half
  the extent it missed, measured against the group's largest view (`PARTIAL_VIEW_SHARE`).
- Reports carrying an error contribute nothing (the caller reports that camera as missing); of a
  camera's several reports only the newest counts (a camera is one view); a detection with
  non-finite coordinates is skipped (a camera's garbage must not cost the others their answer).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon

from drvs.core.errors import InvalidArgument
from drvs.core.geometry import Homography
from drvs.core.mobile import map_homography
from drvs.core.model import Detection, DetectionReport, WorldObject

#: The detector's 1-sigma error of an object's centroid, in image pixels. The HSV detector's contour
#: centroids on the simulator's noisy frames are off by 0.3 px RMS; real cameras add blur, partial
#: occlusion and their calibration's error (about a pixel), which this deliberately covers.
PIXEL_SIGMA = 1.5
#: Floor sigma (metres) of a detection whose camera has no homography the caller knows and whose
#: report carries no areas to derive one from.
FALLBACK_SIGMA_M = 0.10
#: Two outlines overlap when their intersection is at least this share of the smaller one's area.
OVERLAP_FRACTION = 0.2
#: The gate's allowance for an object's size: this share of the smaller member's extent
#: (sqrt of its floor area, or of its bounds' area). Two views of a raised box put its floor
#: projection on different sides of its footprint; their centroids differ by up to about half its size.
SIZE_ALLOWANCE = 0.5
#: A member that saw less of an object than another member: this share of the difference of their
#: extents is added to its sigma (half: its centroid is off by up to half of what it missed).
PARTIAL_VIEW_SHARE = 0.5
#: The gate's width in combined sigmas.
GATE_SIGMAS = 3.0
#: At most this many detections are fused per call (in camera order); the rest are dropped.
#: Cameras bound their own answers; this keeps one call's assignment work bounded whatever arrives.
MAX_DETECTIONS = 2000

_NO_OUTLINE = Polygon()
_UNMATCHED = 1e9


def ground_sampling_distance(h: Homography, floor_xy: tuple[float, float]) -> float:
    """Metres of floor per image pixel at floor_xy for the camera whose image->floor homography is h.

    The square root of |det J|, J the Jacobian of the image->floor mapping at the pixel that sees
    floor_xy (found with the inverse homography): the side of the floor square one pixel covers
    there. For a homography that is |det H| / |w|^3, w the pixel's third homogeneous coordinate
    under H. inf when floor_xy lies on the camera's horizon. InvalidArgument when floor_xy is not
    two finite numbers.
    """
    try:
        x, y = (float(v) for v in floor_xy)
    except (TypeError, ValueError):
        raise InvalidArgument(f"floor_xy: expected two numbers (x, y), got {floor_xy!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InvalidArgument(f"floor_xy: ({x}, {y}) must be finite")
    return float(_gsd(h.matrix, h.inverse().matrix, np.array([[x, y]]))[0])


def _gsd(
    m: NDArray[np.float64], inv: NDArray[np.float64], floor_xy: NDArray[np.float64], abs_det: float | None = None
) -> NDArray[np.float64]:
    """ground_sampling_distance for an (N, 2) array of floor points; m the image->floor matrix, inv its
    inverse, abs_det |det m| (computed here when not given)."""
    if abs_det is None:
        abs_det = abs(float(np.linalg.det(m)))
    pix = floor_xy @ inv[:, :2].T + inv[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pix[:, :2] / pix[:, 2:3]
        w = uv @ m[2, :2] + m[2, 2]
        det = abs_det / np.abs(w) ** 3
    return np.where(np.isfinite(det), np.sqrt(det), np.inf)


#: Homographies whose inverse and |det| `fuse` has computed, by id (the Homography itself is kept,
#: so that an id is not reused while it is here): a camera's registered homography is one object
#: for as long as it is registered, and inverting it for every report was a tenth of a fused
#: request's fusing. Bounded: cleared when full (a mobile camera's homography is new per report).
_SOLVED: dict[int, tuple[Homography, NDArray[np.float64], float]] = {}
_MAX_SOLVED = 256


def _solved(h: Homography) -> tuple[NDArray[np.float64], float]:
    """h's inverse matrix and |det| of its matrix, as Homography.inverse and np.linalg.det give them."""
    hit = _SOLVED.get(id(h))
    if hit is not None and hit[0] is h:
        return hit[1], hit[2]
    inv = h.inverse().matrix
    abs_det = abs(float(np.linalg.det(h.matrix)))
    if len(_SOLVED) >= _MAX_SOLVED:
        _SOLVED.clear()
    _SOLVED[id(h)] = (h, inv, abs_det)
    return inv, abs_det


@dataclass
class _Member:
    det: Detection
    camera_id: str
    capture_time: float
    sigma: float
    extent: float


@dataclass
class _Group:
    members: list[_Member]
    centroid: tuple[float, float]
    sigma: float
    outline: Polygon
    bounds: tuple[float, float, float, float]
    extent: float

    @classmethod
    def of(cls, first: _Member) -> _Group:
        d = first.det
        return cls([first], d.centroid_xy, first.sigma, d.outline, _bounds_of(d.outline, d.bounds), first.extent)

    def add(self, m: _Member) -> None:
        self.members.append(m)
        weights = 1.0 / np.square(_partial_view_sigmas(self.members))
        xy = np.array([x.det.centroid_xy for x in self.members], dtype=np.float64)
        c = weights @ xy / weights.sum()
        self.centroid = (float(c[0]), float(c[1]))
        self.sigma = float(1.0 / math.sqrt(weights.sum()))
        self.outline = _union([x.det.outline for x in self.members if not x.det.outline.is_empty])
        if self.outline.is_empty:
            bs = np.array([x.det.bounds for x in self.members], dtype=np.float64)
            self.bounds = (float(bs[:, 0].min()), float(bs[:, 1].min()), float(bs[:, 2].max()), float(bs[:, 3].max()))
        else:
            self.bounds = _bounds_of(self.outline, self.bounds)
        self.extent = min(self.extent, m.extent)


def _partial_view_sigmas(members: Sequence[_Member]) -> NDArray[np.float64]:
    """Each member's sigma, widened when it saw less of the object than the others did.

    A camera that sees only part of an object (cut by its image's edge, partly hidden) puts the
    centroid in the middle of the part it sees: off by up to half of what it misses. The member's
    extent (sqrt of its floor area) against the largest member's says how much that is; half the
    difference is added in quadrature. Full views of one object differ by little, so this hardly
    changes their weights; a sliver at an image edge counts for almost nothing.
    """
    sigma = np.array([m.sigma for m in members], dtype=np.float64)
    extent = np.array([m.extent for m in members], dtype=np.float64)
    widened: NDArray[np.float64] = np.hypot(sigma, (extent.max() - extent) * PARTIAL_VIEW_SHARE)
    return widened


def _bounds_of(outline: Polygon, fallback: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    if outline.is_empty:
        return fallback
    x0, y0, x1, y1 = outline.bounds
    return (float(x0), float(y0), float(x1), float(y1))


def _union(outlines: Sequence[Polygon]) -> Polygon:
    if not outlines:
        return _NO_OUTLINE
    if len(outlines) == 1:
        return outlines[0]
    merged = shapely.union_all([o if o.is_valid else shapely.make_valid(o) for o in outlines])
    if isinstance(merged, Polygon):
        return merged
    # Members that do not touch (matched by distance): their convex hull covers the object and
    # the gap between the views, which a planner should treat as occupied too.
    hull = merged.convex_hull
    return hull if isinstance(hull, Polygon) else _NO_OUTLINE


def _finite(d: Detection) -> bool:
    isfinite = math.isfinite
    (cx, cy), (x0, y0, x1, y1) = d.centroid_xy, d.bounds
    return isfinite(cx) and isfinite(cy) and isfinite(x0) and isfinite(y0) and isfinite(x1) and isfinite(y1)


def _extent(d: Detection) -> float:
    if d.area_m2 > 0 and math.isfinite(d.area_m2):
        return math.sqrt(d.area_m2)
    x0, y0, x1, y1 = d.bounds
    return math.sqrt(max(0.0, (x1 - x0) * (y1 - y0)))


def _sigmas(detections: Sequence[Detection], h: Homography | None, pixel_sigma: float) -> list[float]:
    """Each detection's 1-sigma floor error at its centroid: pixel_sigma * the camera's GSD there."""
    if h is not None and detections:
        xy = np.array([d.centroid_xy for d in detections], dtype=np.float64)
        inv, abs_det = _solved(h)
        gsd = _gsd(h.matrix, inv, xy, abs_det)
    else:
        gsd = np.full(len(detections), np.inf)
    out = []
    for d, g in zip(detections, gsd.tolist(), strict=True):
        if math.isfinite(g) and g > 0:
            out.append(pixel_sigma * g)
        elif d.area_px > 0 and d.area_m2 > 0:
            # The object's own floor area per image pixel: the GSD averaged over its blob.
            out.append(pixel_sigma * math.sqrt(d.area_m2 / d.area_px))
        else:
            out.append(FALLBACK_SIGMA_M)
    return out


def _type_key(d: Detection) -> tuple[str, int | str]:
    if d.marker_id is not None:
        return ("marker", d.marker_id)
    return ("label", d.label)


def _overlap(a: Polygon, b: Polygon) -> float:
    """Intersection over the smaller area (0 when either outline is missing)."""
    if a.is_empty or b.is_empty:
        return 0.0
    smaller = min(a.area, b.area)
    if smaller <= 0:
        return 0.0
    try:
        return float(a.intersection(b).area / smaller)
    except shapely.errors.GEOSException:
        return 0.0


def _assign(groups: list[_Group], members: list[_Member], *, by_id: bool) -> None:
    """Assign one camera's detections (of one type) to the groups so far; the rest start groups.

    Cost: centroid distance over the gate (3 combined sigmas plus the size allowance). A pair is a
    candidate when that is <= 1 or, failing that, when their outlines overlap; markers (by_id) are
    all candidates. linear_sum_assignment picks the one-to-one matching of least total cost.
    """
    if not groups:
        groups.extend(_Group.of(m) for m in members)
        return
    gxy = np.array([g.centroid for g in groups], dtype=np.float64)
    mxy = np.array([m.det.centroid_xy for m in members], dtype=np.float64)
    dist = np.hypot(gxy[:, None, 0] - mxy[None, :, 0], gxy[:, None, 1] - mxy[None, :, 1])
    gs = np.array([g.sigma for g in groups])[:, None]
    ms = np.array([m.sigma for m in members])[None, :]
    ge = np.array([g.extent for g in groups])[:, None]
    me = np.array([m.extent for m in members])[None, :]
    gate = GATE_SIGMAS * np.hypot(gs, ms) + SIZE_ALLOWANCE * np.minimum(ge, me)
    with np.errstate(divide="ignore", invalid="ignore"):
        normalised = np.where(gate > 0, dist / gate, np.where(dist == 0, 0.0, np.inf))
    if by_id:
        ok = np.isfinite(normalised)
    else:
        ok = normalised <= 1.0
        # Outside the distance gate: the outlines may still overlap (a large or raised object
        # whose views' centroids differ by more than the allowance). Only pairs whose bounds meet.
        gb = np.array([g.bounds for g in groups], dtype=np.float64)
        mb = np.array([m.det.bounds for m in members], dtype=np.float64)
        boxes_meet = (
            (gb[:, None, 0] <= mb[None, :, 2])
            & (mb[None, :, 0] <= gb[:, None, 2])
            & (gb[:, None, 1] <= mb[None, :, 3])
            & (mb[None, :, 1] <= gb[:, None, 3])
        )
        for gi, mi in zip(*np.nonzero(~ok & boxes_meet), strict=True):
            if _overlap(groups[gi].outline, members[mi].det.outline) >= OVERLAP_FRACTION:
                ok[gi, mi] = True
    cost = np.where(ok & np.isfinite(normalised), normalised, _UNMATCHED)
    # Imported here, not at the top: a process that imports drvs.server without serving need not
    # load scipy.optimize; DrvsServer.start imports it before a server serves.
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(cost)
    taken: set[int] = set()
    for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
        if cost[r, c] < _UNMATCHED:
            groups[r].add(members[c])
            taken.add(c)
    groups.extend(_Group.of(m) for i, m in enumerate(members) if i not in taken)


def _circular_mean(angles_deg: Iterable[tuple[float, float]]) -> float | None:
    s = c = 0.0
    seen = False
    for angle, weight in angles_deg:
        seen = True
        s += weight * math.sin(math.radians(angle))
        c += weight * math.cos(math.radians(angle))
    if not seen or (s == 0.0 and c == 0.0):
        return None
    return math.degrees(math.atan2(s, c))


def _world_object(g: _Group, track_id: int) -> WorldObject:
    members = g.members
    outline = g.outline
    area = max(m.det.area_m2 for m in members) if outline.is_empty else float(outline.area)
    first = members[0].det
    sigmas = _partial_view_sigmas(members).tolist()
    heading = _circular_mean(
        (m.det.heading_deg, 1.0 / (s * s))
        for m, s in zip(members, sigmas, strict=True)
        if m.det.heading_deg is not None
    )
    return WorldObject(
        track_id=track_id,
        outline=outline,
        bounds=g.bounds,
        centroid_xy=g.centroid,
        uncertainty_m=g.sigma,
        camera_ids=tuple(sorted({m.camera_id for m in members})),
        last_seen=max(m.capture_time for m in members),
        marker_id=first.marker_id,
        marker_heading_deg=heading,
        label=first.label,
        score=max(m.det.score for m in members),
        area_m2=area,
    )


def _newest_per_camera(reports: Sequence[DetectionReport]) -> list[DetectionReport]:
    """Each camera's newest report without an error (by capture time, then sequence), by camera id.

    A camera that reported twice in one period (a continuous request's reports are not aligned
    with the server's periods) would otherwise see each object twice, and one camera's two
    detections are never merged.
    """
    newest: dict[str, DetectionReport] = {}
    for r in reports:
        if r.error:
            continue
        old = newest.get(r.camera_id)
        if old is None or (r.capture_time, r.sequence) > (old.capture_time, old.sequence):
            newest[r.camera_id] = r
    return [newest[c] for c in sorted(newest)]


def fuse(
    reports: Sequence[DetectionReport],
    homography_of: Callable[[str], Homography | None],
    *,
    pixel_sigma: float = PIXEL_SIGMA,
) -> list[WorldObject]:
    """Merge the detections of one physical object seen by several cameras into one WorldObject.

    reports: the camera reports of one request (or one period); reports with an error contribute
    nothing, and of a camera's several reports only the newest counts. homography_of: camera_id ->
    that camera's image->floor homography, or None when unknown (its precision then comes from the
    detection's own floor area per pixel, or FALLBACK_SIGMA_M); for a mobile camera (a report with
    camera_pose) the homography to its robot's base frame, moved by the report's pose.
    pixel_sigma: the detector's 1-sigma centroid error in pixels.

    Same type only (marker_id for markers: same id merges; else label); match by outline overlap
    or centroid distance gated by the cameras' precision there; two detections of one camera never
    merge; position weighted by 1/sigma^2, sigma = pixel_sigma * GSD; uncertainty_m the fused
    sigma; outline the union of the members'; track_id 1, 2, ... by x then y; velocity 0;
    camera_ids sorted; last_seen the newest capture. The module docstring says why.
    """
    if not (isinstance(pixel_sigma, (int, float)) and math.isfinite(pixel_sigma) and pixel_sigma > 0):
        raise InvalidArgument(f"pixel_sigma: {pixel_sigma!r} must be a positive finite number of pixels")
    homographies: dict[str, Homography | None] = {}
    by_type: dict[tuple[str, int | str], dict[str, list[_Member]]] = {}
    count = 0
    for report in _newest_per_camera(reports):
        cam = report.camera_id
        if cam not in homographies:
            homographies[cam] = homography_of(cam)
        h = homographies[cam]
        if h is not None and report.camera_pose is not None:
            # A mobile camera: its registered homography is to its robot's base frame; the report
            # says where the robot was at capture.
            h = map_homography(h, report.camera_pose)
        detections = [d for d in report.detections if _finite(d)][: max(0, MAX_DETECTIONS - count)]
        count += len(detections)
        for d, sigma in zip(detections, _sigmas(detections, h, pixel_sigma), strict=True):
            member = _Member(d, cam, d.capture_time or report.capture_time, sigma, _extent(d))
            by_type.setdefault(_type_key(d), {}).setdefault(cam, []).append(member)
    groups: list[_Group] = []
    for key, per_camera in by_type.items():
        typed: list[_Group] = []
        for cam in sorted(per_camera):
            _assign(typed, per_camera[cam], by_id=key[0] == "marker")
        groups.extend(typed)

    # The objects' order (and so their track ids): by x, then y of the fused centroid, then marker
    # id and label (each group's first member's, as its object's), sorted stably from group order.
    def order(g: _Group) -> tuple[float, float, int, str]:
        first = g.members[0].det
        return (g.centroid[0], g.centroid[1], first.marker_id if first.marker_id is not None else -1, first.label)

    groups.sort(key=order)
    return [_world_object(g, i + 1) for i, g in enumerate(groups)]
