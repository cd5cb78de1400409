"""`steelscan demo --exit-when-done --keep-serving`: the whole ground station end to end, as a
user runs it, then the report, CSV and MCAP fetched from the URLs it prints, and a clean
stop on SIGTERM."""

import csv
import io
import json
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from mcap.reader import make_reader

pytestmark = pytest.mark.slow  # an end-to-end run


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    log_path = tmp_path / "demo.log"  # a file: a pipe nobody reads would stall the demo once full
    demo_log = log_path.open("w")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "server.cli",
            "demo",
            "--data-dir",
            str(tmp_path),
            "--exit-when-done",
            "--keep-serving",
            "--lanes",
            "2",
            "--time-scale",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=demo_log,
        text=True,
    )
    try:
        assert proc.stdout is not None
        lines = []
        while not (lines and lines[-1].startswith("{")):
            line = proc.stdout.readline()
            assert line, f"demo ended early: {log_path.read_text()[-3000:]}"
            lines.append(line.strip())
        assert lines[0].startswith("Dashboard: http://127.0.0.1:")
        name, password = lines[1].removeprefix("Operator login: ").split(" / ")
        summary = json.loads(lines[-1])
        assert summary["frames"] == summary["frames_sent"] > 0  # every frame stored exactly once
        assert summary["clouds"] == summary["clouds_sent"] > 0
        assert summary["jobs"] == {
            "stitch": "done",
            "map": "done",
            "detect": "done",
            "export": "done",
        }
        assert Path(summary["mosaic_path"]).is_file() and Path(summary["map_path"]).is_file()
        assert 0 <= summary["defects_matched"] <= summary["defects_true"] == 9
        assert summary["defects_found"] >= summary["defects_matched"]
        # every found defect is accounted for: on a true one (first or further piece) or false
        assert summary["defects_placed"] == summary["defects_found"]  # a referenced mosaic
        assert summary["defects_on_true"] + summary["false_alarms"] == summary["defects_placed"]
        # pieces: found defects beyond the first on one true defect (a merge can hide none)
        on_true, pieces = summary["defects_on_true"], summary["defects_in_pieces"]
        assert on_true - summary["defects_matched"] <= pieces < max(on_true, 1)
        assert summary["precision"] == round(
            summary["defects_on_true"] / summary["defects_found"], 3
        )
        # frames placed on the structure
        assert summary["frame_defects_found"] >= summary["frame_defects_matched"] >= 1
        assert isinstance(summary["map_ate_m"], float) and summary["map_ate_m"] < 0.05

        base = lines[0].split()[1].rstrip("/")
        token = httpx.post(
            f"{base}/api/auth/token", data={"username": name, "password": password}
        ).json()["access_token"]
        auth = {"Authorization": f"Bearer {token}"}
        # the URLs need the operator's login
        assert httpx.get(summary["report_pdf_url"]).status_code == 401
        report = httpx.get(summary["report_json_url"], headers=auth).json()
        assert report["summary"]["defects"] == summary["defects_found"]
        pdf = httpx.get(summary["report_pdf_url"], headers=auth, timeout=120)
        assert pdf.status_code == 200 and pdf.content.startswith(b"%PDF")
        rows = list(
            csv.DictReader(
                io.StringIO(
                    httpx.get(summary["report_csv_url"], headers=auth).content.decode("utf-8-sig")
                )
            )
        )
        assert len(rows) == summary["defects_found"]
        mcap = httpx.get(summary["mcap_url"], headers=auth, timeout=120)
        assert mcap.status_code == 200
        stats = make_reader(io.BytesIO(mcap.content)).get_summary().statistics
        assert stats is not None and stats.message_count > summary["frames"] + summary["clouds"]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        demo_log.close()
    # SIGTERM stops it as Ctrl-C does: the robot's session ended, the workers stopped and
    # their queues released (no "leaked semaphore objects" at exit)
    assert proc.returncode == 0, log_path.read_text()[-3000:]
    assert "leaked" not in log_path.read_text()
