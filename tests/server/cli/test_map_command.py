"""``steelscan map`` on foreign input: unorganised clouds, millimetres, empty and all-NaN
clouds, broken files, bad odometry."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from processing.poses import parse_tum
from robot_link.sim.scene_sweeps import SceneSweepConfig, scene_sweep, write_sweep
from robot_link.sim.tof_sweeps import TofSweep
from tests.server.helpers import assert_clean_error, steelscan


@pytest.fixture(scope="module")
def sweep() -> TofSweep:
    return scene_sweep(SceneSweepConfig(kind="cross_frames", seed=8, clouds=10))


def _run(folder: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return steelscan(
        "map",
        str(folder / "clouds"),
        "--out",
        str(folder / "out"),
        "--odometry",
        str(folder / "odom.tum"),
        *extra,
    )


def test_millimetres_are_refused_with_the_flag_to_convert_them(
    tmp_path: Path, sweep: TofSweep
) -> None:
    clouds = write_sweep(sweep, tmp_path)
    for f in sorted(clouds.glob("*.ply")):
        pcd = o3d.io.read_point_cloud(str(f), remove_nan_points=False)
        pcd.points = o3d.utility.Vector3dVector(np.asarray(pcd.points) * 1000)
        o3d.io.write_point_cloud(str(f), pcd)
    assert_clean_error(_run(tmp_path), "--units mm")
    assert not (tmp_path / "out").exists()
    proc = _run(tmp_path, "--units", "mm")
    assert proc.returncode == 0, proc.stderr
    _, poses = parse_tum((tmp_path / "out" / "poses.tum").read_text())
    assert np.abs(poses[:, :3, 3] - sweep.truth[:, :3, 3]).max() < 0.2  # metres, near the truth


def test_empty_and_all_nan_clouds_are_skipped_and_reported(tmp_path: Path, sweep: TofSweep) -> None:
    clouds = write_sweep(sweep, tmp_path)
    nan = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.full_like(sweep.clouds[3], np.nan, dtype=float))
    )
    o3d.io.write_point_cloud(str(clouds / "c0003.ply"), nan)
    (clouds / "c0005.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    (clouds / "sensor.json").unlink()  # c0005 has no points: not organised any more
    proc = _run(tmp_path)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "out" / "map_report.json").read_text())
    assert report["skipped"] == [
        {"file": "c0003.ply", "reason": "every point is NaN or infinite"},
        {"file": "c0005.ply", "reason": "no points"},
    ]
    assert "c0003.ply" in proc.stderr and "c0005.ply" in proc.stderr
    _, poses = parse_tum((tmp_path / "out" / "poses.tum").read_text())
    assert len(poses) == 10 and np.isfinite(poses).all()


def test_unorganised_pcd_from_another_tool_is_mapped(tmp_path: Path, sweep: TofSweep) -> None:
    write_sweep(sweep, tmp_path)
    clouds = tmp_path / "clouds"
    for i, c in enumerate(sweep.clouds):  # NaNs dropped, shuffled, as .pcd
        (clouds / f"c{i:04d}.ply").unlink()
        pts = c[np.isfinite(c).all(axis=1)].astype(float)
        pts = pts[np.random.default_rng(i).permutation(len(pts))]
        o3d.io.write_point_cloud(
            str(clouds / f"c{i:04d}.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        )
    (clouds / "sensor.json").unlink()
    proc = _run(tmp_path)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "out" / "map_report.json").read_text())
    assert report["organised"] is False and report["clouds"] == 10 and report["map_points"] > 1000


def test_a_broken_cloud_file_is_refused_by_name(tmp_path: Path, sweep: TofSweep) -> None:
    clouds = write_sweep(sweep, tmp_path)
    (clouds / "c0002.ply").write_bytes(b"\x00garbage" * 10)
    assert_clean_error(_run(tmp_path), "c0002.ply")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("odometry", "fragment"),
    [
        ("0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n", "odo.tum: TUM line 2: NaN or infinite value"),
        ("0 0 0 0 0 0 0 1\n", "odo.tum: 1 poses for 2 clouds"),
    ],
)
def test_bad_odometry_is_refused_by_file_and_line_before_the_heavy_imports(
    tmp_path: Path, odometry: str, fragment: str
) -> None:
    """Arguments and files are checked before Open3D and SciPy load: the answer is at once."""
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for name in ("a.ply", "b.ply"):
        (clouds / name).write_bytes(b"not read before the odometry is checked")
    (tmp_path / "odo.tum").write_text(odometry)
    probe = (
        "import sys\n"
        "from server.cli.main import main\n"
        f"rc = main(['map', {str(clouds)!r}, '--out', {str(tmp_path / 'out')!r},"
        f" '--odometry', {str(tmp_path / 'odo.tum')!r}])\n"
        "print(rc, sorted(m for m in ('open3d', 'scipy') if m in sys.modules))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=False
    )
    assert proc.stdout.split("\n")[0] == "2 []", proc.stderr
    assert fragment in proc.stderr
    assert not (tmp_path / "out").exists()


def test_frames_join_the_map_and_the_report_says_what_fixed_each_cloud(tmp_path: Path) -> None:
    """``steelscan map --frames``: the downward camera's images with camera.json (its
    intrinsics, T_tof_camera and the frames' times on the odometry's clock)."""
    from processing.metrics import absolute_trajectory_error
    from robot_link.sim.camera_frames import camera_sweep, write_frames
    from robot_link.sim.scene_sweeps import scene_camera

    config = SceneSweepConfig(kind="gusset_joint", seed=12, clouds=16)
    sweep = scene_sweep(config)
    tof = scene_camera(config)
    frames = camera_sweep(sweep.truth, tof.T_robot_tof, 12, tof.structure.mesh)
    write_sweep(sweep, tmp_path)
    write_frames(frames, tmp_path / "frames")
    runs = {}
    for name, extra in (("without", []), ("with", ["--frames", str(tmp_path / "frames")])):
        proc = steelscan(
            "map",
            str(tmp_path / "clouds"),
            "--out",
            str(tmp_path / name),
            "--odometry",
            str(tmp_path / "odom.tum"),
            *extra,
        )
        assert proc.returncode == 0, proc.stderr
        _, poses = parse_tum((tmp_path / name / "poses.tum").read_text())
        runs[name] = absolute_trajectory_error(poses, sweep.truth)
    assert runs["with"] < 0.5 * runs["without"]
    report = json.loads((tmp_path / "with" / "map_report.json").read_text())
    assert report["camera"]["frames"] == len(frames.frames)
    assert report["camera"]["cloud_steps_linked"] == len(sweep.clouds) - 1
    assert 0.005 <= report["camera"]["scale_error"] < 0.05  # one gusset plate: distances agree
    assert report["camera"]["mounting"] is None  # 15 steps: too few to check the mounting
    assert report["camera"]["cloud_steps_carried"] == 0
    assert report["factors"][0]["fixed_by"] == ["odometry"]
    assert all("camera" in f["fixed_by"] for f in report["factors"][1:])
    plain = json.loads((tmp_path / "without" / "map_report.json").read_text())
    assert plain["camera"] is None and all("camera" not in f["fixed_by"] for f in plain["factors"])
    # frames of bare paint along the first lane: that cloud step carried by the steps either side
    for path in sorted((tmp_path / "frames").glob("*.png"))[21:25]:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(path), np.full_like(image, int(image.mean())))
    proc = steelscan(
        "map",
        str(tmp_path / "clouds"),
        "--out",
        str(tmp_path / "bare"),
        "--odometry",
        str(tmp_path / "odom.tum"),
        "--frames",
        str(tmp_path / "frames"),
    )
    assert proc.returncode == 0, proc.stderr
    bare = json.loads((tmp_path / "bare" / "map_report.json").read_text())
    assert bare["camera"]["cloud_steps_linked"] == len(sweep.clouds) - 2
    assert bare["camera"]["cloud_steps_carried"] == 1
    assert [k for k, f in enumerate(bare["factors"]) if "motion" in f["fixed_by"]] == [3]
    assert "camera" not in bare["factors"][3]["fixed_by"]


def test_a_camera_stated_off_its_mount_is_found_and_the_report_gives_the_mounting(
    tmp_path: Path,
) -> None:
    """camera.json's ``T_tof_camera`` 1 cm and 1° off about two axes: the map says so on
    stderr, and ``camera.mounting`` in the report gives the mounting it took, whose
    optical axis meets the plate much nearer the true camera's than the stated one's."""
    from processing.poses import se3_exp
    from robot_link.sim.camera_frames import camera_sweep, write_frames
    from robot_link.sim.scene_sweeps import scene_camera

    config = SceneSweepConfig(kind="cross_frames", seed=4, clouds=40)
    sweep, tof = scene_sweep(config), scene_camera(config)
    frames = camera_sweep(sweep.truth, tof.T_robot_tof, 4, tof.structure.mesh)
    write_sweep(sweep, tmp_path)
    write_frames(frames, tmp_path / "frames")
    spec = json.loads((tmp_path / "frames" / "camera.json").read_text())
    true_mount = np.asarray(spec["T_tof_camera"], float)
    d = np.radians(1)
    stated = true_mount @ se3_exp(np.array([d, d, 0, 0.01, 0.01, 0]))
    spec["T_tof_camera"] = stated.tolist()
    (tmp_path / "frames" / "camera.json").write_text(json.dumps(spec))
    proc = steelscan(
        "map",
        str(tmp_path / "clouds"),
        "--out",
        str(tmp_path / "out"),
        "--odometry",
        str(tmp_path / "odom.tum"),
        "--frames",
        str(tmp_path / "frames"),
    )
    assert proc.returncode == 0, proc.stderr
    assert "the ToF's steps put the camera" in proc.stderr
    mounting = json.loads((tmp_path / "out" / "map_report.json").read_text())["camera"]["mounting"]
    assert mounting["corrected"] and mounting["steps"] >= 20
    assert min(mounting["likelihood_ratio_halves"]) > 11.3

    def axis_foot(T: np.ndarray, distance: float = 0.09) -> np.ndarray:
        """Where the camera's optical axis meets the plate, in the ToF's frame."""
        return T[:3, 3] + distance * T[:3, 2]

    taken = np.asarray(mounting["T_tof_camera"], float)
    off_stated = np.linalg.norm(axis_foot(stated) - axis_foot(true_mount))
    off_taken = np.linalg.norm(axis_foot(taken) - axis_foot(true_mount))
    assert off_taken < off_stated / 2, (off_taken, off_stated)


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"T_tof_camera": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "rigid"),
        ({"fx": -5}, "must be positive"),
        ({"timestamps": [0.0, 1.0]}, "2 timestamps for 3 images"),
        ({"width": None}, "width must be a finite number"),
    ],
)
def test_a_bad_camera_json_is_refused_before_any_work(
    tmp_path: Path, change: dict[str, object], fragment: str
) -> None:
    clouds = tmp_path / "clouds"
    clouds.mkdir()
    for name in ("a.ply", "b.ply", "c.ply"):
        (clouds / name).write_bytes(b"not read before the frames are checked")
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        (frames / f"f{k}.png").write_bytes(b"not read before camera.json is checked")
    camera = {
        "width": 320,
        "height": 240,
        "fx": 266.0,
        "fy": 266.0,
        "cx": 159.5,
        "cy": 119.5,
        "T_tof_camera": np.eye(4).tolist(),
        **change,
    }
    (frames / "camera.json").write_text(json.dumps(camera))
    proc = steelscan("map", str(clouds), "--out", str(tmp_path / "out"), "--frames", str(frames))
    assert_clean_error(proc, fragment)
    assert not (tmp_path / "out").exists()
