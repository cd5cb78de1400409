"""The steelscan command as a user runs it: real processes, real files."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from tests.conftest import LiveServer

DATASET = Path(__file__).resolve().parents[3] / "shared" / "datasets" / "deepcrack-train"


def steelscan(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "server.cli", *args], capture_output=True, text=True, timeout=timeout)


def assert_clean_error(proc: subprocess.CompletedProcess[str], fragment: str) -> None:
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines()[-1].startswith("error: ")
    assert fragment in proc.stderr
    assert "Traceback" not in proc.stderr


def test_create_robot_prints_a_token_alone(tmp_path: Path) -> None:
    proc = steelscan("admin", "create-robot", "r1", "--data-dir", str(tmp_path))
    assert proc.returncode == 0
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1 and len(lines[0]) >= 32
    again = steelscan("admin", "create-robot", "r1", "--data-dir", str(tmp_path))
    assert_clean_error(again, "already exists")


def test_sim_streams_one_route_and_reports_what_it_sent(live_server: LiveServer) -> None:
    proc = steelscan("sim", "--server", live_server.url, "--token", live_server.token, "--exit-when-done", "--lanes", "1", "--time-scale", "0")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    s = httpx.get(f"{live_server.url}/api/sessions/{summary['session_id']}").json()
    assert summary["frames_sent"] == s["frames"] > 5
    assert summary["clouds_sent"] == s["clouds"] == summary["frames_sent"]


def test_sim_with_a_wrong_token_fails_cleanly(live_server: LiveServer) -> None:
    proc = steelscan("sim", "--server", live_server.url, "--token", "nope", "--exit-when-done", "--lanes", "1", timeout=60)
    assert_clean_error(proc, "refused the robot token")


def test_detect_writes_masks_and_defects(tmp_path: Path) -> None:
    img = np.full((120, 160, 3), 150, np.uint8)
    img += np.random.default_rng(0).integers(0, 8, img.shape, dtype=np.uint8)
    cv2.line(img, (10, 20), (150, 100), (40, 40, 40), 2)
    cv2.imwrite(str(tmp_path / "plate.png"), img)
    proc = steelscan("detect", str(tmp_path / "plate.png"), "--out", str(tmp_path / "out"), "--px-per-mm", "4")
    assert proc.returncode == 0, proc.stderr
    mask = cv2.imread(str(tmp_path / "out" / "plate.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (120, 160) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    defects = json.loads((tmp_path / "out" / "defects.json").read_text())
    assert len(defects) == 1 and defects[0]["image"] == "plate.png"
    assert {"id", "bbox", "area_px", "length_px", "max_width_px", "length_mm", "max_width_mm"} <= defects[0].keys()
    assert defects[0]["length_mm"] == pytest.approx(defects[0]["length_px"] / 4, abs=0.01)


@pytest.mark.skipif(not DATASET.is_dir(), reason="shared dataset not present")
def test_detect_runs_on_a_real_crack_image(tmp_path: Path) -> None:
    image = sorted((DATASET / "images").glob("*.jpg"))[0]
    proc = steelscan("detect", str(image), "--out", str(tmp_path), "--method", "sauvola")
    assert proc.returncode == 0, proc.stderr
    assert cv2.imread(str(tmp_path / f"{image.stem}.png")).shape[:2] == cv2.imread(str(image)).shape[:2]


def test_bad_inputs_give_one_line_errors_and_no_output(tmp_path: Path) -> None:
    (tmp_path / "corrupt.jpg").write_bytes(b"\xff\xd8 not really")
    assert_clean_error(steelscan("detect", str(tmp_path / "missing.png"), "--out", str(tmp_path / "o1")), "no such file")
    assert_clean_error(steelscan("detect", str(tmp_path / "corrupt.jpg"), "--out", str(tmp_path / "o2")), "not an image")
    assert not (tmp_path / "o2" / "defects.json").exists()
    (tmp_path / "empty").mkdir()
    assert_clean_error(steelscan("stitch", str(tmp_path / "empty"), "--out", str(tmp_path / "o3")), "no image files")
    assert_clean_error(steelscan("map", str(tmp_path / "empty"), "--out", str(tmp_path / "o4")), "no point cloud files")


def test_stitch_folder_with_odometry_writes_mosaic_and_poses(tmp_path: Path) -> None:
    from tests.processing.test_stitching import cut, texture

    tex = texture(4)
    frames = tmp_path / "frames"
    frames.mkdir()
    lines = []
    for i in range(4):
        cv2.imwrite(str(frames / f"f{i:03d}.png"), cut(tex, 300 + 180 * i, 400))
        lines.append(f"{i} {1.8 * i:.3f} 0 0 0 0 0 1")
    (tmp_path / "odo.tum").write_text("\n".join(lines) + "\n")
    proc = steelscan("stitch", str(frames), "--out", str(tmp_path / "out"), "--odometry", str(tmp_path / "odo.tum"), "--px-per-m", "100")
    assert proc.returncode == 0, proc.stderr
    rows = (tmp_path / "out" / "poses.csv").read_text().splitlines()
    assert rows[0] == "frame,x,y,theta_deg" and len(rows) == 5
    xs = [float(r.split(",")[1]) for r in rows[1:]]
    assert np.allclose(np.diff(xs), 180, atol=0.5)
    (tmp_path / "short.tum").write_text("0 0 0 0 0 0 0 1\n")
    bad = steelscan("stitch", str(frames), "--out", str(tmp_path / "o5"), "--odometry", str(tmp_path / "short.tum"), "--px-per-m", "100")
    assert_clean_error(bad, "1 poses for 4 frames")


@pytest.mark.skipif(not DATASET.is_dir(), reason="shared dataset not present")
def test_bench_detect_prints_json_lines_with_baselines() -> None:
    proc = steelscan("bench", "detect", "--limit", "2")
    assert proc.returncode == 0, proc.stderr
    results = [json.loads(line) for line in proc.stdout.splitlines()]
    names = {r["name"] for r in results}
    assert {"detect.proposed.dsc_tol2", "detect.sauvola_tuned.dsc_tol2", "detect.proposed.time_per_480x320", "detect.peak_detection_per_histogram"} <= names
    for r in results:
        assert {"name", "value", "unit"} <= r.keys()
        if "baseline" in r:
            assert "ratio" in r


def test_bench_with_an_unknown_name_fails_cleanly() -> None:
    assert_clean_error(steelscan("bench", "warp-drive"), "unknown benchmark")


def test_detect_handles_sixteen_bit_tiny_and_constant_images(tmp_path: Path) -> None:
    img16 = np.full((90, 120), 40000, np.uint16)
    cv2.line(img16, (5, 45), (115, 50), 9000, 2)
    cv2.imwrite(str(tmp_path / "deep.png"), img16)
    cv2.imwrite(str(tmp_path / "tiny.png"), np.full((2, 3), 99, np.uint8))
    cv2.imwrite(str(tmp_path / "flat.png"), np.full((50, 60, 3), 128, np.uint8))
    (tmp_path / "empty.png").write_bytes(b"")
    proc = steelscan("detect", *(str(tmp_path / n) for n in ("deep.png", "tiny.png", "flat.png")), "--out", str(tmp_path / "out"))
    assert proc.returncode == 0, proc.stderr
    for name, shape in (("deep", (90, 120)), ("tiny", (2, 3)), ("flat", (50, 60))):
        assert cv2.imread(str(tmp_path / "out" / f"{name}.png"), cv2.IMREAD_UNCHANGED).shape == shape
    defects = json.loads((tmp_path / "out" / "defects.json").read_text())
    assert {d["image"] for d in defects} <= {"deep.png"}
    assert_clean_error(steelscan("detect", str(tmp_path / "empty.png"), "--out", str(tmp_path / "o")), "not an image")


def test_bench_stitch_and_map_measure_against_baselines() -> None:
    proc = steelscan("bench", "stitch", "map", "--limit", "8")
    assert proc.returncode == 0, proc.stderr
    results = {r["name"]: r for r in map(json.loads, proc.stdout.splitlines())}
    assert {"stitch.sim.mean_overlap_error", "stitch.sim.max_centre_error_aligned", "stitch.sim.frames_per_second",
            "map.sim.ate", "map.sim.seconds_per_cloud"} <= results.keys()
    assert results["stitch.sim.mean_overlap_error"]["value"] <= results["stitch.sim.mean_overlap_error"]["baseline"]
    assert results["map.sim.ate"]["value"] < 0.05
