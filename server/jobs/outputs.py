"""Where an attempt writes its result files, and how they become the session's results.

An attempt writes into a staging folder of its own inside the session's results folder
(``results/.attempt-<job>-<attempt>``); the files move into place only in the database
transaction that finishes the job (:func:`server.jobs.leases.finish`), while the attempt
still holds it. A cancelled attempt, one taken over by another worker, or one that failed
leaves the results as they were: its staging folder is removed, and a dead worker's is
removed when the job is claimed again. Two attempts of one job never write the same file.

Moves are renames within one file system (the data directory's contract), so a reader sees
each file either old or new, never half written. A folder (the Deep Zoom pyramid) replaces
the old one by two renames.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

STAGING_PREFIX = ".attempt-"


def staging_dir(results: Path, job_id: int, attempt: int) -> Path:
    """The staging folder of one attempt of a job inside a session's ``results`` folder."""
    return results / f"{STAGING_PREFIX}{job_id}-{attempt}"


def publish(staging: Path, results: Path) -> list[str]:
    """Move every file and folder an attempt left in ``staging`` into ``results``,
    replacing what is there, and remove the staging folder; the names moved. Hidden
    entries (scratch and temporary files) are not results and are dropped. JSON documents
    move last: they describe the images and pyramids beside them."""
    if not staging.is_dir():
        return []
    entries = sorted(
        (e for e in staging.iterdir() if not e.name.startswith(".")),
        key=lambda e: (e.suffix == ".json", e.name),
    )
    for entry in entries:
        target = results / entry.name
        if entry.is_dir() and not entry.is_symlink():
            old = results / f".replaced-{staging.name}-{entry.name}"
            if target.exists():
                os.replace(target, old)
            os.replace(entry, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            os.replace(entry, target)
    shutil.rmtree(staging, ignore_errors=True)
    return [e.name for e in entries]


def discard(staging: Path) -> None:
    """Remove an attempt's staging folder and everything in it."""
    shutil.rmtree(staging, ignore_errors=True)


def discard_earlier(results: Path, job_id: int, attempt: int) -> list[str]:
    """Remove the staging folders of the job's attempts before ``attempt`` (their workers
    died, or were taken over: what they wrote never becomes a result); the names removed."""
    if not results.is_dir():
        return []
    removed = []
    for d in results.glob(f"{STAGING_PREFIX}{job_id}-*"):
        number = d.name.rsplit("-", 1)[-1]
        if number.isdigit() and int(number) < attempt:
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d.name)
    return removed
