"""`steelscan demo --exit-when-done`: the whole ground station end to end, as a user runs it."""

import json
import subprocess
import sys
from pathlib import Path


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "server.cli", "demo", "--data-dir", str(tmp_path), "--exit-when-done", "--lanes", "2", "--time-scale", "0"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert lines[0].startswith("Dashboard: http://127.0.0.1:")
    summary = json.loads(lines[-1])
    assert summary["frames"] == summary["frames_sent"] > 0  # every frame stored exactly once
    assert summary["clouds"] == summary["clouds_sent"] > 0
    assert summary["jobs"] == {"stitch": "done", "map": "done", "detect": "done"}
    assert Path(summary["mosaic_path"]).is_file() and Path(summary["map_path"]).is_file()
    assert 0 <= summary["defects_matched"] <= summary["defects_true"] == 9
    assert summary["defects_found"] >= summary["defects_matched"]
    assert summary["frame_defects_found"] >= summary["frame_defects_matched"] >= 1  # frames placed on the structure
    assert isinstance(summary["map_ate_m"], float) and summary["map_ate_m"] < 0.05
    for key in ("session_id", "report_json_url"):
        assert summary[key]
