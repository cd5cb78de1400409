"""The ``export`` job: the whole session as an MCAP file."""

from __future__ import annotations

from typing import Any

from server.jobs.context import JobContext
from server.reports.mcap_export import export_session


def run_export(ctx: JobContext) -> dict[str, Any]:
    """The whole session as an MCAP file (``results/session.mcap``), written under a temporary
    name and renamed when complete."""
    out = ctx.results_dir()
    tmp = out / f".session.mcap.{ctx.job_id}.tmp"
    try:
        with ctx.factory() as db, tmp.open("wb") as fh:
            counts = export_session(db, ctx.files, ctx.session_id, fh, progress=ctx.progress)
        tmp.replace(out / "session.mcap")
    finally:
        tmp.unlink(missing_ok=True)
    return {
        "mcap_path": str(out / "session.mcap"),
        "bytes": (out / "session.mcap").stat().st_size,
        **counts,
    }
