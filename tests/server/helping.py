"""A job context whose parts are all taken by a helper: another process, as a second
worker would be, that works through each plan before the job's worker looks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from server.jobs.context import JobContext
from server.jobs.parts import FolderFanout
from server.storage.files import SessionFiles

HELPER = (
    "import json, sys; from server.jobs.parts import help_with; "
    "print(json.dumps(help_with(sys.argv[1], sys.argv[2], 60.0)))"
)


def helped_context(data_dir: Path, session_id: str = "s") -> tuple[JobContext, list[int]]:
    """A job's context over ``data_dir`` and the list of how many chunks the helper did,
    one entry per plan it was asked to help with."""
    done_by_helper: list[int] = []

    def ask(job_id: int, name: str, helpers: int) -> None:
        out = subprocess.run(
            [sys.executable, "-c", HELPER, str(data_dir), name],
            capture_output=True,
            text=True,
            check=True,
        )
        done_by_helper.append(json.loads(out.stdout.splitlines()[-1]))

    ctx = JobContext(
        1,
        session_id,
        None,  # type: ignore[arg-type]
        SessionFiles(data_dir),
        attempt=1,
        fanout=FolderFanout(ask, 1, lease_s=60.0),
    )
    return ctx, done_by_helper
