"""Listing: the live cameras, page by page, as ListCameras (and the live view) describe them."""

from __future__ import annotations

import bisect
import math

from shapely.geometry import Polygon

from drvs.core.model import check_frame, check_id
from drvs.server.registry import CameraEntry, Registry
from drvs.v1 import registry_pb2
from drvs.wire.convert import polygon_to_pb, pose_to_pb

#: ListCameras: cameras per reply unless the caller asks for fewer, and the most it may ask for.
#: A camera's entry is at most about 4 kB (id, address, 16 detector kinds, a field of view of at
#: most about 70 vertices): 500 of them stay far below the 4 MB message limit.
DEFAULT_PAGE_SIZE = 500
MAX_PAGE_SIZE = 500


def list_cameras(
    registry: Registry, region: Polygon | None = None, page_token: str = "", page_size: int = 0, frame: str = ""
) -> tuple[list[CameraEntry], str]:
    """One page of the live cameras (those of `frame`, "" every frame, that see `region`, if
    given), sorted by id, after the id `page_token` names; `page_size` 0 or above MAX_PAGE_SIZE
    means MAX_PAGE_SIZE. Returns the page and the next page's token ("" on the last page)."""
    if page_token:
        check_id(page_token, "page_token")
    only = check_frame(frame) if frame else None
    size = min(page_size or DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE)
    if region is None:
        entries = [e for e in registry.cameras() if only is None or e.frame == only]
    else:
        entries = registry.cameras_seeing(region, frame=only)
    # Both lists are sorted by camera id: a page starts after the id its token names.
    start = bisect.bisect_right([e.camera_id for e in entries], page_token) if page_token else 0
    more = len(entries) > start + size
    entries = entries[start : start + size]
    return entries, entries[-1].camera_id if more else ""


def camera_info(registry: Registry, e: CameraEntry) -> registry_pb2.CameraInfo:
    """A camera as ListCameras describes it."""
    info = registry_pb2.CameraInfo(
        camera_id=e.camera_id,
        address=e.address,
        field_of_view=polygon_to_pb(e.field_of_view) if not e.field_of_view.is_empty else None,
        detector_kinds=sorted(e.detector_kinds),
        # (0 on a registry shared in etcd: etcd's lease decides, renewed through any server.)
        lease_remaining_s=left if math.isfinite(left := registry.remaining_s(e.camera_id)) else 0.0,
        frame=e.frame,
    )
    state = registry.mobile_state(e.camera_id)
    if state is not None:
        info.mobile = True
        info.unroutable = registry.unroutable(e.camera_id)
        if state.pose is not None:
            info.pose.CopyFrom(pose_to_pb(state.pose))
            info.pose_age_s = registry.pose_age_s(e.camera_id)
    return info
