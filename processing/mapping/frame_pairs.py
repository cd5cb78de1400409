"""The downward camera's consecutive frames registered pair by pair, as the stitcher
registers them (:func:`processing.stitching.registration.register_pair`: sub-pixel
translation and rotation), for the map's camera factors (:mod:`.camera_motion`)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from processing.poses import compose_se2, half_se2

Guess = tuple[NDArray[np.float64], tuple[float, ...]]  # (dx, dy px, dθ) and turns to search
# a pair the last motion does not predict is searched over this much more turn (a robot
# entering or leaving a turn between two frames)
TURN_SEARCH_DEG = 10.0


def frame_deltas(
    frames: Sequence[NDArray[np.uint8]],
    predicted_px: Sequence[NDArray[np.floating]] | None = None,
) -> list[NDArray[np.float64] | None]:
    """Each consecutive frame pair's registration (dx, dy px, dθ: frame k + 1 in frame k's
    centred pixels; None where it fails), searched from the last pair's motion (the robot
    drives smoothly), from it over a range of turns (entering or leaving a turn), from the
    pair's phase correlation (any shift; Hann-windowed, so that the frames' borders do not
    pull it to no shift) and last from ``predicted_px`` (the odometry's). A match that
    correlates less than this route's matches usually do (:func:`_usual_score`) is not
    taken at once: the other starts are searched too and the best match is kept (a turn
    begun between two frames can leave a weaker match at the last motion's turn). A frame
    that matches neither neighbour is stepped over (:func:`_bridged`)."""
    from processing.stitching.registration import Level, register_pair

    turns = tuple(np.radians(np.arange(-TURN_SEARCH_DEG, TURN_SEARCH_DEG + 1e-9, 2.5)))
    out: list[NDArray[np.float64] | None] = []
    scores: list[float] = []
    last = np.zeros(3)
    following = Level.of(np.asarray(frames[0], np.float32)) if len(frames) else None
    window: NDArray[np.float32] | None = None
    for k in range(len(frames) - 1):  # two frames prepared at a time: any length fits
        current, following = following, Level.of(np.asarray(frames[k + 1], np.float32))
        assert current is not None
        if window is None:
            h, w = current.full.image.shape
            window = np.asarray(cv2.createHanningWindow((w, h), cv2.CV_32F), np.float32)

        def guesses(
            k: int = k,
            last: NDArray[np.float64] = last,
            a: Level = current,
            b: Level = following,
            window: NDArray[np.float32] = window,
        ) -> Iterator[Guess]:
            yield last, (0.0,)
            yield last, turns
            # windowed by hand: given a window, OpenCV multiplies the images in place
            (sx, sy), _ = cv2.phaseCorrelate(a.full.image * window, b.full.image * window)
            yield np.array([-sx, -sy, last[2]]), turns
            if predicted_px is not None:
                yield np.asarray(predicted_px[k], np.float64), turns

        usual = _usual_score(scores)
        best: tuple[NDArray[np.float64], float, float, float] | None = None
        for guess, angles in guesses():
            found = register_pair(current, following, guess, angles=angles)
            if found is not None and (best is None or found[1] > best[1]):
                best = found
            if best is not None and best[1] >= usual:
                break
        out.append(None if best is None else best[0])
        if best is not None:
            last = best[0]
            scores.append(best[1])
    return _bridged(frames, out)


def _bridged(
    frames: Sequence[NDArray[np.uint8]], deltas: list[NDArray[np.float64] | None]
) -> list[NDArray[np.float64] | None]:
    """``deltas`` where a frame k + 1 matched neither frame k nor frame k + 2 (smooth paint,
    a blurred or overexposed frame): frame k registered to frame k + 2 directly (from two
    of the last motion) and the step split into two equal halves."""
    from processing.stitching.registration import Level, register_pair

    out = list(deltas)
    last = np.zeros(3)
    for k in range(len(out) - 1):
        if out[k] is not None:
            last = np.asarray(out[k], np.float64)
            continue
        if out[k + 1] is not None or k + 2 >= len(frames):
            continue
        found = register_pair(
            Level.of(np.asarray(frames[k], np.float32)),
            Level.of(np.asarray(frames[k + 2], np.float32)),
            compose_se2(last, last),
        )
        if found is not None:
            out[k] = out[k + 1] = half_se2(found[0])
    return out


def _usual_score(scores: Sequence[float], recent: int = 50) -> float:
    """The correlation a match of this route is taken at without searching further: the
    ``recent`` matches' median less three robust deviations (1 before five matches: every
    start is searched)."""
    if len(scores) < 5:
        return 1.0
    s = np.asarray(scores[-recent:], np.float64)
    median = float(np.median(s))
    return median - 3 * 1.4826 * float(np.median(np.abs(s - median)))
