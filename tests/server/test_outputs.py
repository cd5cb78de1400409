"""An attempt's result files: published into the session's results in one step, or dropped."""

from __future__ import annotations

from pathlib import Path

from server.jobs.outputs import discard_earlier, publish, staging_dir


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
