"""The steelscan command as a user runs it: real processes, real files."""

import json
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from tests.conftest import LiveServer
from tests.server.helpers import assert_clean_error, steelscan

DATASET = Path(__file__).resolve().parents[4] / "shared" / "datasets" / "deepcrack-train"


def test_create_robot_prints_a_token_alone(tmp_path: Path) -> None:
    proc = steelscan("admin", "create-robot", "r1", "--data-dir", str(tmp_path))
    assert proc.returncode == 0
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1 and len(lines[0]) >= 32
    again = steelscan("admin", "create-robot", "r1", "--data-dir", str(tmp_path))
    assert_clean_error(again, "already exists")


def test_sim_streams_one_route_and_reports_what_it_sent(live_server: LiveServer) -> None:
    proc = steelscan(
        "sim",
        "--server",
        live_server.url,
        f"--token={live_server.token}",
        "--exit-when-done",
        "--lanes",
        "1",
        "--time-scale",
        "0",
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    s = httpx.get(f"{live_server.url}/api/sessions/{summary['session_id']}").json()
    assert summary["frames_sent"] == s["frames"] > 5
    assert summary["clouds_sent"] == s["clouds"] == summary["frames_sent"]


def test_sim_with_a_wrong_token_fails_cleanly(live_server: LiveServer) -> None:
    proc = steelscan(
        "sim",
        "--server",
        live_server.url,
        "--token",
        "nope",
        "--exit-when-done",
        "--lanes",
        "1",
        timeout=60,
    )
    assert_clean_error(proc, "refused the robot token")


def test_detect_writes_masks_and_defects(tmp_path: Path) -> None:
    img = np.full((120, 160, 3), 150, np.uint8)
    img += np.random.default_rng(0).integers(0, 8, img.shape, dtype=np.uint8)
    cv2.line(img, (10, 20), (150, 100), (40, 40, 40), 2)
    cv2.imwrite(str(tmp_path / "plate.png"), img)
    proc = steelscan(
        "detect", str(tmp_path / "plate.png"), "--out", str(tmp_path / "out"), "--px-per-mm", "4"
    )
    assert proc.returncode == 0, proc.stderr
    mask = cv2.imread(str(tmp_path / "out" / "plate.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (120, 160) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    defects = json.loads((tmp_path / "out" / "defects.json").read_text())
    assert len(defects) == 1 and defects[0]["image"] == "plate.png"
    assert {
        "id",
        "bbox",
        "area_px",
        "length_px",
        "max_width_px",
        "length_mm",
        "max_width_mm",
    } <= defects[0].keys()
    assert defects[0]["length_mm"] == pytest.approx(defects[0]["length_px"] / 4, abs=0.01)


@pytest.mark.skipif(not DATASET.is_dir(), reason="shared dataset not present")
def test_detect_runs_on_a_real_crack_image(tmp_path: Path) -> None:
    image = sorted((DATASET / "images").glob("*.jpg"))[0]
    proc = steelscan("detect", str(image), "--out", str(tmp_path), "--method", "sauvola")
    assert proc.returncode == 0, proc.stderr
    assert (
        cv2.imread(str(tmp_path / f"{image.stem}.png")).shape[:2]
        == cv2.imread(str(image)).shape[:2]
    )


def test_bad_inputs_give_one_line_errors_and_no_output(tmp_path: Path) -> None:
    (tmp_path / "corrupt.jpg").write_bytes(b"\xff\xd8 not really")
    assert_clean_error(
        steelscan("detect", str(tmp_path / "missing.png"), "--out", str(tmp_path / "o1")),
        "no such file",
    )
    assert_clean_error(
        steelscan("detect", str(tmp_path / "corrupt.jpg"), "--out", str(tmp_path / "o2")),
        "not an image",
    )
    assert not (tmp_path / "o2" / "defects.json").exists()
    (tmp_path / "empty").mkdir()
    assert_clean_error(
        steelscan("stitch", str(tmp_path / "empty"), "--out", str(tmp_path / "o3")),
        "no image files",
    )
    assert_clean_error(
        steelscan("map", str(tmp_path / "empty"), "--out", str(tmp_path / "o4")),
        "no point cloud files",
    )


def test_stitch_folder_with_odometry_writes_mosaic_pyramid_and_poses(tmp_path: Path) -> None:
    from processing.poses import format_tum, relative_se2, se2_to_se3
    from tests.processing.helpers import sweep

    s = sweep(frames=8, seed=12)
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, jpeg in enumerate(s.frames):
        (frames / f"f{i:03d}.jpg").write_bytes(jpeg)
    # metres at 100 px/m
    T = np.array([se2_to_se3(p[0] / 100, p[1] / 100, p[2]) for p in s.odometry])
    (tmp_path / "odo.tum").write_text(format_tum(np.arange(8, dtype=float), T))
    out = tmp_path / "out"
    proc = steelscan(
        "stitch",
        str(frames),
        "--out",
        str(out),
        "--odometry",
        str(tmp_path / "odo.tum"),
        "--px-per-m",
        "100",
    )
    assert proc.returncode == 0, proc.stderr
    rows = (out / "poses.csv").read_text().splitlines()
    assert rows[0] == "frame,x,y,theta_deg" and len(rows) == 9
    est = np.array([[float(v) for v in r.split(",")[1:]] for r in rows[1:]])
    est[:, 2] = np.radians(est[:, 2])
    for k in range(7):  # consecutive frames placed as they truly are, rotation included
        assert (
            np.abs(relative_se2(est[k], est[k + 1]) - relative_se2(s.truth[k], s.truth[k + 1]))[
                :2
            ].max()
            < 0.2
        )
    mosaic = cv2.imread(str(out / "mosaic.png"))
    assert mosaic.shape[0] > 240 and mosaic.shape[1] > 320
    world = json.loads((out / "mosaic.json").read_text())
    assert (
        world["width_px"] == mosaic.shape[1]
        and len(world["frames"]) == 8
        and world["world_referenced"]
    )
    dzi = (out / "mosaic.dzi").read_text()
    assert f'Width="{mosaic.shape[1]}"' in dzi and 'TileSize="254"' in dzi
    top = max(int(p.name) for p in (out / "mosaic_files").iterdir() if p.is_dir())
    assert cv2.imread(str(out / "mosaic_files" / str(top) / "0_0.jpg")) is not None
    assert cv2.imread(str(out / "mosaic_files" / "0" / "0_0.jpg")).shape[:2] == (1, 1)
    (tmp_path / "short.tum").write_text("0 0 0 0 0 0 0 1\n")
    bad = steelscan(
        "stitch",
        str(frames),
        "--out",
        str(tmp_path / "o5"),
        "--odometry",
        str(tmp_path / "short.tum"),
        "--px-per-m",
        "100",
    )
    assert_clean_error(bad, "1 poses for 8 frames")


@pytest.mark.parametrize("w_first", [False, True], ids=["tum-order", "w-first"])
def test_map_folder_of_organised_clouds_with_odometry_beats_the_odometry(
    tmp_path: Path, w_first: bool
) -> None:
    """``steelscan map`` on a ToF sweep that returns to its start, as files (PLY with NaN
    rows, sensor.json, TUM odometry): map.ply and one pose per cloud, closer to the truth
    than the odometry it started from; odometry written with its quaternions w-first is
    recognised by the clouds, read so and reported."""
    import open3d as o3d

    from processing.metrics import absolute_trajectory_error
    from processing.poses import format_tum, parse_tum
    from robot_link.sim.tof_sweeps import TofSweepConfig, tof_sweep

    sweep = tof_sweep(TofSweepConfig(seed=21))
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for i, c in enumerate(sweep.clouds):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c.astype(np.float64)))
        assert o3d.io.write_point_cloud(str(clouds / f"c{i:03d}.ply"), pcd, write_ascii=False)
    (clouds / "sensor.json").write_text(json.dumps(sweep.intrinsics))
    tum = format_tum(np.arange(len(sweep.clouds), dtype=float), sweep.odometry)
    if w_first:  # t tx ty tz qw qx qy qz
        lines = [ln.split() for ln in tum.splitlines()[1:]]
        tum = "\n".join(" ".join(p[:4] + [p[7]] + p[4:7]) for p in lines) + "\n"
    (tmp_path / "odo.tum").write_text(tum)
    out = tmp_path / "out"
    proc = steelscan("map", str(clouds), "--out", str(out), "--odometry", str(tmp_path / "odo.tum"))
    assert proc.returncode == 0, proc.stderr
    order = json.loads((out / "map_report.json").read_text())["odometry"]["quaternion_order"]
    assert order == ("qw qx qy qz" if w_first else "qx qy qz qw")
    assert ("read w-first" in proc.stderr) == w_first
    _, poses = parse_tum((out / "poses.tum").read_text())
    assert poses.shape == (len(sweep.clouds), 4, 4)
    ate = absolute_trajectory_error(poses, sweep.truth)
    assert ate < 0.75 * absolute_trajectory_error(sweep.odometry, sweep.truth)
    assert ate < 0.0025 * 3.38  # the drift target: 0.25 % of the sensor's 3.38 m path
    assert len(o3d.io.read_point_cloud(str(out / "map.ply")).points) > 10_000


def test_stitch_refuses_corrupt_or_mismatched_frames_and_writes_nothing(tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((60, 80, 3), 100, np.uint8))
    (frames / "f3.png").write_bytes(b"\x89PNG garbage")
    assert_clean_error(steelscan("stitch", str(frames), "--out", str(tmp_path / "o1")), "f3.png")
    (frames / "f3.png").unlink()
    cv2.imwrite(str(frames / "f3.png"), np.full((61, 80, 3), 100, np.uint8))
    assert_clean_error(
        steelscan("stitch", str(frames), "--out", str(tmp_path / "o2")),
        "differs from the first frame",
    )
    cv2.imwrite(str(frames / "f3.png"), np.full((60, 80), 4000, np.uint16))
    assert_clean_error(steelscan("stitch", str(frames), "--out", str(tmp_path / "o3")), "8-bit")
    assert not any((tmp_path / name).exists() for name in ("o1", "o2", "o3"))


@pytest.mark.skipif(not DATASET.is_dir(), reason="shared dataset not present")
@pytest.mark.slow  # a whole benchmark
def test_bench_detect_prints_json_lines_with_baselines() -> None:
    proc = steelscan("bench", "detect", "--dataset", str(DATASET), "--limit", "6")
    assert proc.returncode == 0, proc.stderr
    results = [json.loads(line) for line in proc.stdout.splitlines()]
    names = {r["name"] for r in results}
    set_name = DATASET.name
    assert {
        *(f"detect.{set_name}.{m}.dsc_tol2" for m in ("sauvola", "paper", "proposed", "learned")),
        f"detect.{set_name}.lowlight.learned.dsc_tol2",
        f"detect.{set_name}.learned_held_back.dsc_tol2",
        f"detect.{set_name}.learned_fit.dsc_tol2",
        f"detect.{set_name}.learned_confidence.ece",
        "detect.learned.time_per_544x384",
        "detect.learned.mosaic_throughput",
    } <= names
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
    proc = steelscan(
        "detect",
        *(str(tmp_path / n) for n in ("deep.png", "tiny.png", "flat.png")),
        "--out",
        str(tmp_path / "out"),
    )
    assert proc.returncode == 0, proc.stderr
    for name, shape in (("deep", (90, 120)), ("tiny", (2, 3)), ("flat", (50, 60))):
        assert (
            cv2.imread(str(tmp_path / "out" / f"{name}.png"), cv2.IMREAD_UNCHANGED).shape == shape
        )
    defects = json.loads((tmp_path / "out" / "defects.json").read_text())
    assert {d["image"] for d in defects} <= {"deep.png"}
    assert_clean_error(
        steelscan("detect", str(tmp_path / "empty.png"), "--out", str(tmp_path / "o")),
        "not an image",
    )


@pytest.mark.slow  # a whole benchmark
def test_bench_stitch_measures_against_baselines() -> None:
    proc = steelscan("bench", "stitch", "--limit", "8")
    assert proc.returncode == 0, proc.stderr
    results = {r["name"]: r for r in map(json.loads, proc.stdout.splitlines())}
    for surface in ("textured", "painted_steel"):
        mean = results[f"stitch.{surface}.lawnmower.mean_overlap_error"]
        # far better than odometry alone
        assert mean["value"] < 0.5 and mean["value"] < mean["baseline"]
        assert (
            results[f"stitch.{surface}.lawnmower.ms_per_frame"]["baseline_is"]
            == "cv2.Stitcher SCANS"
        )
        assert f"stitch.{surface}.lawnmower.images_only.end_drift" in results
        ecc = results[
            f"stitch.{surface}.straight.ecc_end_drift"
        ]  # OpenCV's ECC refinement on the same pairs
        assert ecc["mean_overlap_error"] < 0.5 and ecc["ms_per_pair"] > 0
    spread = results["stitch.straight_runs.end_drift_rms"]
    assert spread["runs"] == len(spread["drifts"]) == len(spread["baseline_drifts"]) >= 8


@pytest.mark.slow  # a whole benchmark
def test_bench_map_measures_against_baselines() -> None:
    proc = steelscan("bench", "map", "--limit", "8")
    assert proc.returncode == 0, proc.stderr
    results = {r["name"]: r for r in map(json.loads, proc.stdout.splitlines())}
    assert {
        "map.sweep31.ate",
        "map.sweep31.drift",
        "map.sweep31.rpe",
        "map.sweep31.ms_per_cloud",
    } <= results.keys()
    assert results["map.sweep31.ate"]["value"] < 0.05
    for kind in ("i_girder", "box_girder", "cross_frames", "truss", "gusset_joint"):
        drift = results[f"map.structure.{kind}.drift_mean"]
        assert drift["seeds"] == 1 and drift["value"] > 0 and "odometry_mean" in drift
        assert 0 < drift["bound_mean"] < drift["floor_mean"] < drift["odometry_mean"]
    assert results["map.structure.i_girder.whole_command"]["clouds"] == 8  # the first type's


@pytest.mark.slow  # a whole benchmark
def test_bench_ingest_counts_every_frame_it_sends() -> None:
    proc = steelscan("bench", "ingest", "--limit", "2")
    assert proc.returncode == 0, proc.stderr
    results = {r["name"]: r for r in map(json.loads, proc.stdout.splitlines())}
    assert results["ingest.lost"]["value"] == 0 and results["ingest.lost"]["acked"] > 0
    assert results["ingest.frames_per_second"]["baseline_is"] == "bare websockets echo on loopback"
    assert (
        results["ingest.ack_latency_p99"]["value"] >= results["ingest.ack_latency_p50"]["value"] > 0
    )
