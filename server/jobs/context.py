"""What a job body gets (:class:`JobContext`) and the helpers every job shares."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from server.storage.files import SessionFiles, write_atomic
from server.storage.models import InspectionSession, Job


@dataclass
class JobContext:
    """What a job body gets: its row's ids and parameters, the database and the data
    directory."""

    job_id: int
    session_id: str
    factory: sessionmaker[Session]
    files: SessionFiles
    params: dict[str, Any] = field(default_factory=dict)

    def progress(self, fraction: float, message: str = "") -> None:
        """Record progress (0-1) and a short message."""
        with self.factory() as db:
            job = db.get(Job, self.job_id)
            if job is not None:
                job.progress = float(min(max(fraction, 0.0), 1.0))
                job.message = message
                db.commit()

    def session(self) -> InspectionSession:
        """The job's session row."""
        with self.factory() as db:
            s = db.get(InspectionSession, self.session_id)
            if s is None:
                raise ValueError(f"session {self.session_id} no longer exists")
            return s

    def results_dir(self) -> Path:
        """Folder for this session's result files."""
        d = self.files.results_dir(self.session_id)
        d.mkdir(parents=True, exist_ok=True)
        return d


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an image as PNG, atomically."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"could not encode {path.name}")
    write_atomic(path, buf.tobytes())


def params_record(params: Any) -> dict[str, Any]:
    """A parameters dataclass as JSON-ready data (for the report's parameter table)."""
    return json.loads(json.dumps(asdict(params), default=str))
