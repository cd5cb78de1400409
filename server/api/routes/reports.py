"""Reports and exports of a session: report.json, report.pdf, defects.csv/json, the MCAP log."""

from __future__ import annotations

import uuid
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse
from sqlalchemy import select

from processing.coverage import CoverageParams
from server.api.accounts import has_role
from server.api.deps import CurrentUser, OperatorUser, SessionDep, StateDep, get_current_user
from server.api.queries import get_session_or_404
from server.api.schemas import JobPublic
from server.api.uploads import receive_upload
from server.reports.content import build_report
from server.reports.pdf import write_pdf
from server.reports.tables import defects_csv
from server.storage.models import InspectionSession, Job, JobState, Role, SessionStatus

router = APIRouter(
    prefix="/api/sessions", tags=["reports"], dependencies=[Depends(get_current_user)]
)
MCAP_NAME = "session.mcap"
IMPORT_PATH = "/api/sessions/import"


def _base_url(request: Request) -> str:
    return str(request.base_url).rstrip("/")


def _filename(s: InspectionSession, suffix: str) -> str:
    safe = (
        "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in s.structure)[:60].strip("_")
        or "session"
    )
    return f"{safe}-{s.started_at:%Y%m%d}-{s.id[:8]}{suffix}"


@router.get("/{session_id}/report.json")
def read_report_json(
    db: SessionDep, state: StateDep, request: Request, session_id: str
) -> dict[str, Any]:
    """The inspection report as data: cover, summary, defects, results, parameters, notes on what is missing."""
    get_session_or_404(db, session_id)
    return build_report(
        db, state.files, session_id, base_url=_base_url(request), coverage=_coverage(state)
    )


def _coverage(state: Any) -> CoverageParams:
    return CoverageParams(required_mm_per_px=state.settings.coverage_mm_per_px)


@router.get("/{session_id}/report.pdf", response_class=FileResponse)
async def read_report_pdf(
    db: SessionDep, state: StateDep, request: Request, session_id: str
) -> FileResponse:
    """The inspection report as PDF, made fresh (it shows the latest review)."""
    s = get_session_or_404(db, session_id)
    out = state.files.results_dir(session_id)
    out.mkdir(parents=True, exist_ok=True)
    path = await run_in_threadpool(
        write_pdf,
        db,
        state.files,
        session_id,
        out / "report.pdf",
        base_url=_base_url(request),
        coverage=_coverage(state),
    )
    return FileResponse(path, media_type="application/pdf", filename=_filename(s, "-report.pdf"))


@router.get("/{session_id}/defects.csv", response_class=StreamingResponse)
def read_defects_csv(
    db: SessionDep, state: StateDep, request: Request, session_id: str
) -> StreamingResponse:
    """The report's defects as CSV (UTF-8 with BOM, one row per defect, sizes in mm, position in m)."""
    s = get_session_or_404(db, session_id)
    records = build_report(db, state.files, session_id, base_url=_base_url(request))["defects"]
    return StreamingResponse(
        defects_csv(records),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{_filename(s, "-defects.csv")}"'},
    )


@router.get("/{session_id}/defects.json")
def read_defects_json(
    db: SessionDep, state: StateDep, request: Request, session_id: str
) -> list[dict[str, Any]]:
    """The report's defects as a JSON list (the rows of defects.csv)."""
    get_session_or_404(db, session_id)
    return build_report(db, state.files, session_id, base_url=_base_url(request))["defects"]


def _mcap_fresh(db: SessionDep, s: InspectionSession) -> Job | None:
    """The export job whose MCAP is still current, if any: the session has ended and no
    processing job finished after it."""
    jobs = list(db.scalars(select(Job).where(Job.session_id == s.id).order_by(Job.id)))
    exports = [
        j
        for j in jobs
        if j.kind == "export" and j.state == JobState.done and j.finished_at is not None
    ]
    if not exports or s.status != SessionStatus.ended:
        return None
    last = exports[-1]
    later = [
        j
        for j in jobs
        if j.kind != "export"
        and j.state == JobState.done  # a failed or cancelled run changed no result
        and j.finished_at is not None
        and j.finished_at > last.finished_at
    ]
    return None if later else last


@router.get(
    "/{session_id}/export.mcap",
    response_class=FileResponse,
    responses={
        202: {
            "model": JobPublic,
            "description": "the export is being made: poll the job, then ask again",
        }
    },
)
def read_session_mcap(db: SessionDep, state: StateDep, session_id: str, user: CurrentUser) -> Any:
    """The whole session as an MCAP file (Foxglove schemas: images, clouds, poses, telemetry),
    streamed from disk. When it is not made yet or is out of date, an export job is queued
    and 202 returned with it (queueing one needs the operator role)."""
    s = get_session_or_404(db, session_id)
    path = state.files.results_dir(session_id) / MCAP_NAME
    if _mcap_fresh(db, s) is not None and path.is_file():
        return FileResponse(
            path, media_type="application/octet-stream", filename=_filename(s, ".mcap")
        )
    pending = db.scalar(
        select(Job)
        .where(
            Job.session_id == session_id,
            Job.kind == "export",
            Job.state.in_([JobState.queued, JobState.running]),
        )
        .order_by(Job.id.desc())
    )
    if pending is None:
        if not has_role(user, Role.operator):
            raise HTTPException(
                status.HTTP_403_FORBIDDEN,
                "the MCAP of this session is not made yet; making it needs the operator role",
            )
        job_id = state.jobs.enqueue(session_id, "export")
        pending = db.get(Job, job_id)
    assert pending is not None
    body = JobPublic.model_validate(pending).model_dump(mode="json")
    return JSONResponse(
        body,
        status_code=status.HTTP_202_ACCEPTED,
        headers={"Retry-After": "2", "Location": f"/api/jobs/{pending.id}"},
    )


@router.post(
    "/import",
    status_code=status.HTTP_201_CREATED,
    openapi_extra={
        "requestBody": {
            "content": {
                "multipart/form-data": {
                    "schema": {
                        "type": "object",
                        "properties": {"file": {"type": "string", "format": "binary"}},
                        "required": ["file"],
                    }
                },
                "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
            },
            "required": True,
        }
    },
)
async def import_mcap(
    request: Request, db: SessionDep, state: StateDep, _: OperatorUser
) -> dict[str, Any]:
    """Import a session's MCAP log (as exported by this station) into a new session (operator
    role): a form's ``file`` field, or the file as the body. The caller is authenticated
    before the upload is read; it streams into the data directory within the import limit
    and the disk reserve (507 when the disk is short). Frames and clouds are stored byte
    for byte."""
    from server.reports.mcap_import import McapImportError, import_session

    tmp_dir = state.files.data_dir / "imports"
    tmp_dir.mkdir(parents=True, exist_ok=True)
    tmp = tmp_dir / f".upload-{uuid.uuid4().hex}.mcap"
    reserve = state.ingest.reserve
    try:
        name = await receive_upload(
            request,
            tmp,
            state.settings.max_import_bytes,
            # an import stops a reserve's worth earlier than robots do: their data comes first
            (lambda n: reserve.claim(n, headroom=reserve.reserve_bytes))
            if reserve is not None
            else (lambda _: None),
        )
        try:
            result = await run_in_threadpool(import_session, db, state.files, tmp)
        except McapImportError as exc:
            raise HTTPException(422, str(exc).replace(tmp.name, name)) from None
    finally:
        tmp.unlink(missing_ok=True)
    if state.settings.auto_process:  # processed as a session that ends
        result["jobs"] = await run_in_threadpool(state.jobs.enqueue_pipeline, result["session_id"])
    return result
