"""A session's ToF point clouds: the list, each payload as sent, each as PLY."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response
from sqlalchemy import select

from robot_link.clouds import decode_cloud
from server.api.deps import SessionDep, StateDep, get_current_user
from server.api.queries import (
    MAX_INT,
    Seq,
    count_rows,
    get_cloud_or_404,
    get_session_or_404,
    read_payload,
)
from server.api.schemas import CloudsPublic
from server.errors import NotFound
from server.storage.models import Cloud
from server.storage.ply import ply_bytes

router = APIRouter(
    prefix="/api/sessions", tags=["clouds"], dependencies=[Depends(get_current_user)]
)


@router.get("/{session_id}/clouds", response_model=CloudsPublic)
def read_clouds(
    db: SessionDep,
    session_id: str,
    skip: Annotated[int, Query(ge=0, le=MAX_INT)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> CloudsPublic:
    """ToF point clouds of a session in sequence order."""
    get_session_or_404(db, session_id)
    rows = db.scalars(
        select(Cloud)
        .where(Cloud.session_id == session_id)
        .order_by(Cloud.seq)
        .offset(skip)
        .limit(limit)
    )
    return CloudsPublic(data=list(rows), count=count_rows(db, Cloud, session_id))  # type: ignore[arg-type]


@router.get("/{session_id}/clouds/{seq}/raw", response_class=Response)
def read_cloud_raw(db: SessionDep, state: StateDep, session_id: str, seq: Seq) -> Response:
    """A cloud's payload as the robot sent it (16-bit depth PNG in mm, or float32 xyz)."""
    cloud = get_cloud_or_404(db, session_id, seq)
    png = cloud.encoding == "png16_depth_mm"
    name = f"cloud-{seq:010d}.{'png' if png else 'xyz'}"
    return Response(
        read_payload(state.files, cloud, f"cloud {seq} of session {session_id}"),
        media_type="image/png" if png else "application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )


@router.get("/{session_id}/clouds/{seq}/points.ply", response_class=Response)
def read_cloud_ply(db: SessionDep, state: StateDep, session_id: str, seq: Seq) -> Response:
    """A cloud's valid points in the sensor frame (metres) as binary PLY."""
    cloud = get_cloud_or_404(db, session_id, seq)
    meta = {
        "encoding": cloud.encoding,
        "width": cloud.width,
        "height": cloud.height,
        **cloud.intrinsics,
    }
    try:
        points = decode_cloud(state.files.payload(cloud), meta)
    except (OSError, ValueError) as exc:
        raise NotFound(f"cloud {seq} of session {session_id} cannot be read: {exc}") from None
    return Response(
        ply_bytes(points),
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="cloud-{seq:06d}.ply"'},
    )
