"""The ``export`` job: the whole session as an MCAP file."""

from __future__ import annotations

from typing import Any

from server.jobs.context import JobContext
from server.reports.mcap_export import export_session


def run_export(ctx: JobContext) -> dict[str, Any]:
    """The whole session as an MCAP file (``results/session.mcap``), written in the
    attempt's staging folder and published when the job is done."""
    path = ctx.output_dir() / "session.mcap"
    with ctx.factory() as db, path.open("wb") as fh:
        counts = export_session(db, ctx.files, ctx.session_id, fh, progress=ctx.progress)
    return {
        "mcap_path": str(ctx.results_dir() / "session.mcap"),
        "bytes": path.stat().st_size,
        **counts,
    }
