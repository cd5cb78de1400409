"""An attempt's result files: published into the session's results in one step, or dropped;
a real detect run cancelled as it ends changes neither the defects nor the masks."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from server.jobs.outputs import discard_earlier, publish, staging_dir
from tests.conftest import LiveServer


def test_publish_replaces_files_and_folders_and_drops_scratch(tmp_path: Path) -> None:
    results = tmp_path / "results"
    (results / "mosaic_files" / "0").mkdir(parents=True)
    (results / "mosaic_files" / "0" / "0_0.jpg").write_bytes(b"old tile")
    (results / "mosaic_files" / "9").mkdir()  # a level the new pyramid does not have
    (results / "mosaic.png").write_bytes(b"old")
    (results / "trajectory.tum").write_bytes(b"another job's")
    staging = staging_dir(results, 4, 2)
    (staging / "mosaic_files" / "0").mkdir(parents=True)
    (staging / "mosaic_files" / "0" / "0_0.jpg").write_bytes(b"new tile")
    (staging / "mosaic.png").write_bytes(b"new")
    (staging / "mosaic.json").write_text("{}")
    (staging / ".mosaic-scratch").mkdir()
    (staging / ".tmp-1.png").write_bytes(b"half")

    moved = publish(staging, results)

    assert moved == ["mosaic.png", "mosaic_files", "mosaic.json"]  # the document last
    assert (results / "mosaic.png").read_bytes() == b"new"
    assert (results / "mosaic_files" / "0" / "0_0.jpg").read_bytes() == b"new tile"
    assert not (results / "mosaic_files" / "9").exists()  # the old pyramid is gone whole
    assert (results / "trajectory.tum").read_bytes() == b"another job's"
    assert sorted(p.name for p in results.iterdir()) == [
        "mosaic.json",
        "mosaic.png",
        "mosaic_files",
        "trajectory.tum",
    ]  # no staging, scratch or replaced folder left


def test_publish_of_an_attempt_that_wrote_nothing_changes_nothing(tmp_path: Path) -> None:
    results = tmp_path / "results"
    results.mkdir()
    (results / "map.ply").write_bytes(b"kept")
    assert publish(staging_dir(results, 1, 1), results) == []
    assert [p.name for p in results.iterdir()] == ["map.ply"]


def test_earlier_attempts_staging_is_removed_when_the_job_is_claimed_again(
    tmp_path: Path,
) -> None:
    results = tmp_path / "results"
    for job, attempt in ((3, 1), (3, 2), (3, 3), (13, 1)):
        staging_dir(results, job, attempt).mkdir(parents=True)
    assert sorted(discard_earlier(results, 3, 3)) == [".attempt-3-1", ".attempt-3-2"]
    assert sorted(p.name for p in results.iterdir()) == [".attempt-13-1", ".attempt-3-3"]


def test_a_detect_run_cancelled_as_it_ends_changes_no_defect_nor_file(
    inspected: tuple[LiveServer, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A cancel that arrives after the detect job did all its work, just before it is
    recorded done: the session's defects and masks stay those of the run before, the report
    still has its detection, and the attempt's own files are gone."""
    from server.jobs import leases
    from server.jobs.detect import run_detect
    from server.jobs.worker import JOB_KINDS, factory_for, run_job
    from server.storage.models import Job, JobState

    live, sid = inspected
    api = f"{live.url}/api/sessions/{sid}"
    results = live.settings.data_dir / "sessions" / sid / "results"
    defects = httpx.get(f"{api}/defects", params={"limit": 1000}).json()["data"]
    masks = {n: (results / n).read_bytes() for n in ("crack_mask.png", "corrosion_mask.png")}
    factory = factory_for(live.settings.database_url)
    with factory() as db:  # a job no worker holds (as if its worker died), for this process
        job = Job(session_id=sid, kind="detect", state=JobState.running)
        db.add(job)
        db.commit()
        job_id = job.id
    seen: dict[str, list[str]] = {}

    def detect_then_cancelled(ctx):  # type: ignore[no-untyped-def]
        result = run_detect(ctx)
        seen["staged"] = sorted(p.name for p in ctx.output_dir().iterdir())
        assert leases.cancel(ctx.factory, ctx.job_id, "inspector")
        return result

    monkeypatch.setitem(JOB_KINDS, "detect", detect_then_cancelled)
    outcome = run_job(job_id, live.settings.database_url, str(live.settings.data_dir))
    assert outcome == "lost"
    assert {"crack_mask.png", "corrosion_mask.png"} <= set(seen["staged"])  # it did write them
    after = httpx.get(f"{api}/defects", params={"limit": 1000}).json()["data"]
    assert [d["id"] for d in after] == [d["id"] for d in defects]
    assert all((results / n).read_bytes() == data for n, data in masks.items())
    assert not [p.name for p in results.iterdir() if p.name.startswith(".")]
    with factory() as db:
        assert db.get(Job, job_id).state == JobState.cancelled  # type: ignore[union-attr]
    assert httpx.get(f"{api}/report.json").json()["missing"] == []  # the results still stand
