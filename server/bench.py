"""``steelscan bench``: accuracy and speed of each processing stage against baselines run
in the same process. Each result is one JSON line with ``name``, ``value``, ``unit`` and,
where there is a baseline, ``baseline`` and ``ratio``."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.detection import detect_cracks
from processing.peaks import dominant_peaks
from server.config import PROJECT_ROOT
from server.errors import CommandError

DEFAULT_CRACK_DATASET = PROJECT_ROOT.parent / "shared" / "datasets" / "deepcrack-train"
Result = dict[str, Any]


@dataclass
class Pooled:
    """Pixel counts pooled over a set of images, strict and with a tolerance."""

    tp_p: int = 0
    fp: int = 0
    tp_t: int = 0
    fn: int = 0

    def add(self, pred: NDArray[np.bool_], truth: NDArray[np.bool_], tolerance_px: int) -> None:
        """Accumulate one image's counts."""
        if tolerance_px:
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tolerance_px + 1,) * 2)
            t_near = cv2.dilate(truth.astype(np.uint8), k) > 0
            p_near = cv2.dilate(pred.astype(np.uint8), k) > 0
        else:
            t_near, p_near = truth, pred
        self.tp_p += int((pred & t_near).sum())
        self.fp += int((pred & ~t_near).sum())
        self.tp_t += int((truth & p_near).sum())
        self.fn += int((truth & ~p_near).sum())

    def scores(self) -> tuple[float, float, float]:
        """PI, SI, DSC (paper eqs. 18-20) of the pooled counts."""
        pi = self.tp_p / max(self.tp_p + self.fp, 1)
        si = self.tp_t / max(self.tp_t + self.fn, 1)
        dsc = 2 * pi * si / (pi + si) if pi + si else 0.0
        return round(pi, 4), round(si, 4), round(dsc, 4)


def low_light(image: NDArray[np.uint8], rng: np.random.Generator) -> NDArray[np.uint8]:
    """Uneven low light: illumination falling to ~20 % across the frame, gamma, sensor noise."""
    gray = image.astype(np.float32) / 255.0
    h, w = gray.shape[:2]
    angle = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = (np.cos(angle) * xx / w + np.sin(angle) * yy / h)
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
    light = 1.0 - 0.8 * t
    out = (gray * (light if gray.ndim == 2 else light[..., None])) ** 1.4
    out = out * 255 + rng.normal(0, 4, out.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


def load_crack_dataset(root: Path, limit: int | None) -> list[tuple[str, NDArray[np.uint8], NDArray[np.bool_]]]:
    """(name, image, truth) pairs of a folder with ``images/`` and ``masks/``."""
    images = sorted((root / "images").glob("*.jpg")) + sorted((root / "images").glob("*.png"))
    if not images:
        raise CommandError(f"{root}: no images/ with .jpg or .png files (use --dataset)")
    out = []
    for p in images[:limit]:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(root / "masks" / f"{p.stem}.png"), cv2.IMREAD_GRAYSCALE)
        if img is None or mask is None:
            continue
        out.append((p.name, img, mask > 127))
    return out


def sauvola_tuned(image: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """The strongest Sauvola baseline found on the dev split: window 61, k 0.4, components
    under 300 px removed (scikit-image's implementation)."""
    from skimage.filters import threshold_sauvola

    from processing.detection import remove_small, to_gray

    gray = to_gray(image)
    return remove_small(gray < threshold_sauvola(gray, window_size=61, k=0.4), 300)


def _method(name: str) -> Callable[[NDArray[np.uint8]], NDArray[np.bool_]]:
    if name == "sauvola_tuned":
        return sauvola_tuned
    return lambda img: detect_cracks(img, method=name)  # type: ignore[arg-type]


def bench_detect(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Pooled PI/SI/DSC (strict and 2-px tolerant) of every method on the dataset and on a
    low-light variant, against the tuned Sauvola baseline; time per 480x320 image against
    scikit-image's Sauvola; mosaic throughput; peak detection time per histogram."""
    data = load_crack_dataset(dataset or DEFAULT_CRACK_DATASET, limit)
    rng = np.random.default_rng(0)
    variants = {"": data, "lowlight_": [(n, low_light(i, rng), t) for n, i, t in data]}
    for prefix, items in variants.items():
        baseline = 0.0
        for method in ("sauvola_tuned", "sauvola", "otsu", "paper", "proposed"):
            strict, tol = Pooled(), Pooled()
            fn = _method(method)
            for _, img, truth in items:
                pred = fn(img)
                strict.add(pred, truth, 0)
                tol.add(pred, truth, 2)
            pi, si, dsc = tol.scores()
            spi, ssi, sdsc = strict.scores()
            baseline = baseline or dsc
            yield {"name": f"detect.{prefix}{method}.dsc_tol2", "value": dsc, "unit": "dsc", "baseline": baseline,
                   "ratio": round(dsc / max(baseline, 1e-9), 3), "pi": pi, "si": si,
                   "strict": {"pi": spi, "si": ssi, "dsc": sdsc}, "images": len(items)}
    small = [cv2.resize(i, (480, 320), interpolation=cv2.INTER_AREA) for _, i, _ in data[:60]]
    times = {}
    for method in ("sauvola", "proposed", "paper"):
        fn = _method(method)
        t0 = time.perf_counter()
        for img in small:
            fn(img)
        times[method] = 1000 * (time.perf_counter() - t0) / len(small)
        yield {"name": f"detect.{method}.time_per_480x320", "value": round(times[method], 2), "unit": "ms",
               "baseline": round(times["sauvola"], 2), "ratio": round(times[method] / times["sauvola"], 3)}
    yield from _mosaic_throughput()
    hists = [np.bincount(cv2.cvtColor(i, cv2.COLOR_BGR2GRAY).ravel(), minlength=256) for _, i, _ in data[:50]]
    t0 = time.perf_counter()
    for h in hists:
        dominant_peaks(h)
    yield {"name": "detect.peak_detection_per_histogram", "value": round(1000 * (time.perf_counter() - t0) / len(hists), 3), "unit": "ms"}


def _mosaic_throughput() -> Iterator[Result]:
    """Megapixels per second of tiled detection on a simulated 9-megapixel mosaic."""
    from skimage.filters import threshold_sauvola

    from processing.detection import detect_cracks_tiled
    from robot_link.sim.structure import make_structure

    mosaic = make_structure(11).texture
    mp = mosaic.shape[0] * mosaic.shape[1] / 1e6
    t0 = time.perf_counter()
    gray = cv2.cvtColor(mosaic, cv2.COLOR_BGR2GRAY)
    _ = gray < threshold_sauvola(gray, window_size=25, k=0.2)
    base = mp / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    detect_cracks_tiled(mosaic)
    ours = mp / (time.perf_counter() - t0)
    yield {"name": "detect.mosaic_throughput", "value": round(ours, 2), "unit": "MP/s", "baseline": round(base, 2),
           "ratio": round(ours / base, 3), "megapixels": round(mp, 1)}


def _decode(jpegs: list[bytes]) -> list[NDArray[np.uint8]]:
    return [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR) for j in jpegs]


def bench_stitch(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Frame-centre error against the simulator's true camera poses (odometry as the initial
    guess, as on the robot) and frames per second against OpenCV's SCANS stitcher."""
    from processing.poses import compose_se2
    from processing.stitching import stitch_frames
    from robot_link.sim.inspection import SimConfig
    from robot_link.sim.recording import record_inspection

    rec = record_inspection(SimConfig(lanes=3, seed=21))
    frames = _decode(rec.frames[:limit])
    cam = rec.calibration["camera"]
    px_per_m = float(cam["px_per_m"])
    T_rc = np.array(cam["T_robot_camera"])
    odo = np.array([compose_se2(np.array([p["x"], p["y"], p["yaw"]]), T_rc) for p in rec.frame_odometry[: len(frames)]])
    truth = rec.frame_truth[: len(frames), :2] * px_per_m
    t0 = time.perf_counter()
    mosaic = stitch_frames(frames, odo, px_per_m=px_per_m)
    ours_fps = len(frames) / (time.perf_counter() - t0)

    size = max(frames[0].shape[:2])
    pairs = [(i, j) for i in range(len(truth)) for j in range(i + 1, len(truth)) if np.linalg.norm(truth[j] - truth[i]) < 0.8 * size]

    def overlap_errors(est: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.array([np.linalg.norm((est[j] - est[i]) - (truth[j] - truth[i])) for i, j in pairs])

    def aligned_errors(est: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.linalg.norm(_rigid_align_2d(est, truth) - truth, axis=1)

    ours_est, odo_est = mosaic.frame_poses_px[:, :2], odo[:, :2] * px_per_m
    for label, fn in (("overlap_error", overlap_errors), ("centre_error_aligned", aligned_errors)):
        e, e_odo = fn(ours_est), fn(odo_est)
        yield {"name": f"stitch.sim.mean_{label}", "value": round(float(e.mean()), 3), "unit": "px",
               "baseline": round(float(e_odo.mean()), 3), "ratio": round(float(e.mean() / max(e_odo.mean(), 1e-9)), 3),
               "baseline_is": "odometry alone", "frames": len(frames), "pairs": len(pairs)}
        yield {"name": f"stitch.sim.max_{label}", "value": round(float(e.max()), 3), "unit": "px",
               "baseline": round(float(e_odo.max()), 3), "ratio": round(float(e.max() / max(e_odo.max(), 1e-9)), 3)}
    lane = frames[:12]
    stitcher = cv2.Stitcher_create(cv2.Stitcher_SCANS)
    t0 = time.perf_counter()
    try:
        code, _ = stitcher.stitch(lane)
        status = "ok" if code == cv2.Stitcher_OK else f"failed with status {code}"
    except cv2.error as exc:
        status = f"raised: {str(exc).strip().splitlines()[-1][:120]}"
    cv_fps = len(lane) / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    stitch_frames(lane, odo[:12], px_per_m=px_per_m)
    lane_fps = len(lane) / (time.perf_counter() - t0)
    yield {"name": "stitch.sim.frames_per_second", "value": round(lane_fps, 2), "unit": "frames/s", "baseline": round(cv_fps, 2),
           "ratio": round(lane_fps / cv_fps, 2), "baseline_is": "cv2.Stitcher SCANS (time to its result or failure)",
           "baseline_status": status, "all_frames_fps": round(ours_fps, 2)}


def _rigid_align_2d(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """``src`` points moved by the rotation and translation that best fit them to ``dst``."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((dst - md).T @ (src - ms))
    R = U @ np.diag([1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return (src - ms) @ R.T + md


def bench_map(dataset: Path | None = None, limit: int | None = None) -> Iterator[Result]:
    """Trajectory error (ATE) of the map against the simulator's true ToF poses, and time,
    against Open3D's tutorial pipeline (FPFH + RANSAC global registration, then
    point-to-plane ICP, cloud to cloud) on the same clouds."""
    from processing.mapping import IcpParams, preprocess, register_clouds
    from processing.metrics import absolute_trajectory_error
    from processing.poses import se2_to_se3
    from robot_link.clouds import decode_cloud
    from robot_link.sim.inspection import SimConfig
    from robot_link.sim.recording import record_inspection

    rec = record_inspection(SimConfig(lanes=2, seed=23))
    assert rec.result is not None
    T_rt = np.array(rec.calibration["tof"]["T_robot_tof"])
    clouds, guess, truth = [], [], []
    for m in rec.cloud_messages[:limit]:
        pts = decode_cloud(m.payload, m.meta)
        if not np.isfinite(pts).all(axis=1).any():
            continue
        p = m.meta["pose"]
        clouds.append(pts)
        guess.append(se2_to_se3(p["x"], p["y"], p["yaw"]) @ T_rt)
        truth.append(rec.result.cloud_poses_true[m.seq])
    guess_a, truth_a = np.array(guess), np.array(truth)
    t0 = time.perf_counter()
    ours = register_clouds(clouds, guess_a)
    ours_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tutorial = _open3d_tutorial_poses([preprocess(c, IcpParams()) for c in clouds], guess_a[0])
    base_s = time.perf_counter() - t0
    ate, ate_base = absolute_trajectory_error(ours.poses, truth_a), absolute_trajectory_error(tutorial, truth_a)
    yield {"name": "map.sim.ate", "value": round(ate, 4), "unit": "m", "baseline": round(ate_base, 4),
           "ratio": round(ate / max(ate_base, 1e-9), 3), "baseline_is": "Open3D tutorial FPFH+RANSAC+ICP",
           "odometry_ate": round(absolute_trajectory_error(guess_a, truth_a), 4), "clouds": len(clouds)}
    yield {"name": "map.sim.seconds_per_cloud", "value": round(ours_s / len(clouds), 4), "unit": "s",
           "baseline": round(base_s / len(clouds), 4), "ratio": round(ours_s / base_s, 3)}


def _open3d_tutorial_poses(pcds: list[Any], T0: NDArray[np.float64]) -> NDArray[np.float64]:
    """Open3D's global-registration tutorial, applied cloud to cloud and chained."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    voxel = 0.02
    feats = [reg.compute_fpfh_feature(p, o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 5, max_nn=100)) for p in pcds]
    poses = [T0]
    for i in range(1, len(pcds)):
        ransac = reg.registration_ransac_based_on_feature_matching(
            pcds[i], pcds[i - 1], feats[i], feats[i - 1], True, voxel * 1.5,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(voxel * 1.5)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        icp = reg.registration_icp(pcds[i], pcds[i - 1], voxel * 0.4 * 3, ransac.transformation,
                                   reg.TransformationEstimationPointToPlane())
        poses.append(poses[-1] @ icp.transformation)
    return np.array(poses)


BENCHMARKS: dict[str, Callable[..., Iterator[Result]]] = {"detect": bench_detect, "stitch": bench_stitch, "map": bench_map}


def run_benchmarks(names: list[str], *, dataset: Path | None = None, limit: int | None = None) -> None:
    """Run the named benchmarks (all when empty), printing one JSON object per line."""
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        raise CommandError(f"unknown benchmark(s) {unknown}; known: {sorted(BENCHMARKS)}")
    for name in names or list(BENCHMARKS):
        for result in BENCHMARKS[name](dataset=dataset, limit=limit):
            print(json.dumps(result), flush=True)
