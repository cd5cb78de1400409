"""OpenCV's baselines for the stitch benchmark on the same frames: ``cv2.Stitcher``
(SCANS) for a whole sweep, and ECC refinement (Euclidean, every pixel of the overlap) of
each consecutive pair."""

from __future__ import annotations

import time

import cv2
import numpy as np
from numpy.typing import NDArray

from bench.common import Result, rigid_align_2d, similarity_align_2d
from processing.poses import delta_of_map, frame_i_to_j, relative_se2
from processing.stitching.registration import overlap_rect
from robot_link.sim.sweeps import Sweep


class Jpegs:
    """A sweep's frames decoded on demand (decoding is part of the measured cost)."""

    def __init__(self, frames: list[bytes]) -> None:
        self.frames = frames

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, k: int) -> NDArray[np.uint8]:
        return cv2.imdecode(np.frombuffer(self.frames[k], np.uint8), cv2.IMREAD_COLOR)


def centre_errors(
    est_xy: NDArray[np.float64], truth_xy: NDArray[np.float64], *, with_scale: bool = False
) -> NDArray[np.float64]:
    """Frame-centre errors (px) after the best rigid (or similarity) fit to the truth."""
    fit = similarity_align_2d if with_scale else rigid_align_2d
    return np.linalg.norm(fit(est_xy, truth_xy) - truth_xy, axis=1)


def opencv_stitcher(sweep: Sweep) -> tuple[NDArray[np.float64] | None, float, str, int]:
    """cv2.Stitcher (SCANS) on the same frames: frame centres (NaN for frames it dropped),
    seconds, status and how many frames it kept."""
    frames = [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR) for j in sweep.frames]
    stitcher = cv2.Stitcher_create(cv2.Stitcher_SCANS)
    t0 = time.perf_counter()
    try:
        code, _ = stitcher.stitch(frames)
    except cv2.error as exc:
        return (
            None,
            time.perf_counter() - t0,
            f"raised: {str(exc).strip().splitlines()[-1][:100]}",
            0,
        )
    seconds = time.perf_counter() - t0
    if code != cv2.Stitcher_OK:
        return None, seconds, f"failed with status {code}", 0
    h, w = frames[0].shape[:2]
    centres = np.full((len(frames), 2), np.nan)
    for k, cam in zip(np.asarray(stitcher.component()).ravel(), stitcher.cameras()):
        centres[int(k)] = (np.asarray(cam.R, float) @ np.array([(w - 1) / 2, (h - 1) / 2, 1.0]))[:2]
    return centres, seconds, "ok", int(np.isfinite(centres[:, 0]).sum())


def ecc_steps(sweep: Sweep, poses: NDArray[np.float64]) -> tuple[list[NDArray[np.float64]], float]:
    """Each consecutive pair refined by OpenCV's ECC (Euclidean, every pixel of the
    overlap, a standard dense refinement) from our own step; and seconds per pair."""
    size = sweep.config.frame_size
    frames = Jpegs(sweep.frames)
    grey = [
        cv2.cvtColor(frames[k], cv2.COLOR_BGR2GRAY).astype(np.float32) for k in range(len(frames))
    ]
    steps, seconds = [], 0.0
    for k in range(len(grey) - 1):
        start = relative_se2(poses[k], poses[k + 1])
        M = frame_i_to_j(start, size)
        rect = overlap_rect(M, size, 8, 0.15)
        if rect is None:
            steps.append(start)
            continue
        x0, y0, x1, y1 = rect
        # template pixel -> frame k+1
        W = W0 = (M @ np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1.0]]))[:2].astype(np.float32)
        t0 = time.perf_counter()
        try:
            _, W = cv2.findTransformECC(
                grey[k][y0:y1, x0:x1],
                grey[k + 1],
                W0.copy(),
                cv2.MOTION_EUCLIDEAN,
                (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-7),
                None,
                5,
            )
        except cv2.error:  # did not converge: keep the start
            W = W0
        seconds += time.perf_counter() - t0
        steps.append(
            delta_of_map(
                np.vstack([W, [0, 0, 1]]) @ np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]]), size
            )
        )
    return steps, seconds / max(1, len(grey) - 1)


def opencv_baseline(sweep: Sweep, ms: float) -> Result:
    """cv2.Stitcher's time per frame on the same frames against ours (``ms``), its status,
    and its frame-centre errors (after the best similarity fit) where it kept 3 frames."""
    n = len(sweep.frames)
    centres_cv, cv_seconds, status, kept = opencv_stitcher(sweep)
    cv_ms = 1000 * cv_seconds / n
    baseline: Result = {
        "baseline": round(cv_ms, 1),
        "ratio": round(ms / cv_ms, 4),
        "baseline_is": "cv2.Stitcher SCANS",
        "baseline_status": status,
        "baseline_frames_kept": kept,
    }
    if centres_cv is not None and kept >= 3:
        ok = np.isfinite(centres_cv[:, 0])
        e = centre_errors(centres_cv[ok], sweep.truth[ok, :2], with_scale=True)
        baseline.update(
            {
                "baseline_mean_centre_error_px": round(float(e.mean()), 2),
                "baseline_max_centre_error_px": round(float(e.max()), 2),
            }
        )
    return baseline
