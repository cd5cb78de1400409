"""Global pose estimation for mosaics: every overlapping pair registered, all poses solved together.

Every pair of frames that overlaps is registered (:mod:`processing.stitching.registration`), and all
frame poses are solved together as a 2D pose graph (:mod:`processing.stitching.pose_graph`), so error
does not accumulate along the robot's path. Without odometry, the first guesses come from
phase correlation (:mod:`processing.stitching.phase`).

A pose is (x, y, θ): the frame centre in mosaic pixels and the angle from the mosaic's
x axis to the frame's x axis (radians, positive from x towards y).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from processing.poses import chain_se2, relative_se2, se2_matrix
from processing.stitching.phase import PHASE_SCALES, PhaseView, phase_candidates
from processing.stitching.pose_graph import candidate_pairs, measurement_residuals, solve_pose_graph
from processing.stitching.registration import (
    Level,
    PairMeasurement,
    RegistrationParams,
    register_pair,
)


@dataclass
class PoseEstimate:
    """Solved poses, which frames are held by image measurements, and the pairs used."""

    poses: NDArray[np.float64]
    confident: NDArray[np.bool_]
    measurements: list[PairMeasurement]
    rejected: int


CONSECUTIVE_RUN = 8  # consecutive pairs registered by one thread in a row


@dataclass(frozen=True)
class PairRequest:
    """A pair to register: frame j in frame i's coordinates from ``start`` (dx, dy, dθ),
    with each of ``tries`` in turn until one verifies."""

    i: int
    j: int
    start: NDArray[np.float64]
    tries: tuple[RegistrationParams, ...]
    angles: tuple[float, ...] = (0.0,)  # turns searched around the start's (radians)


PairSpread = Callable[[Sequence[PairRequest]], list[PairMeasurement | None]]
"""Registers many pairs, results in order: on this process's threads by default, or spread
over other processes that load the frames themselves (a job queue's workers)."""


def measure_pair(load: Callable[[int], Level], request: PairRequest) -> PairMeasurement | None:
    """One :class:`PairRequest` registered with frames from ``load`` (None: no try verified)."""
    for params in request.tries:
        found = register_pair(
            load(request.i), load(request.j), request.start, params, angles=request.angles
        )
        if found is not None:
            delta, score, mi, mj = found
            return PairMeasurement(request.i, request.j, delta, score, mi, mj)
    return None


def _runs(count: int, workers: int) -> list[range]:
    """0..count split into runs of about :data:`CONSECUTIVE_RUN`, as many per worker."""
    pieces = max(1, workers) * max(1, -(-count // (max(1, workers) * CONSECUTIVE_RUN)))
    edges = [round(count * k / pieces) for k in range(pieces + 1)]
    return [range(a, b) for a, b in pairwise(edges) if b > a]


def _nearest_measured(
    measurements: Sequence[PairMeasurement | None], k: int, count: int = 2
) -> list[int]:
    """Indices of the ``count`` measured entries nearest to entry k (the one before first
    when two are as near)."""
    found: list[int] = []
    # outwards from k: no scan of a whole long session per pair
    for step in range(1, len(measurements)):
        for j in (k - step, k + step):
            if 0 <= j < len(measurements) and measurements[j] is not None:
                found.append(j)
                if len(found) == count:
                    return found
    return found


# turns searched when there is no odometry (climbed from 0)
BLIND_ANGLES = tuple(np.radians([-8.0, -6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0, 8.0]))
# a verified guess this good ends the search (true matches ≥ 0.98, false ones ≤ 0.88, measured)
SURE_MATCH = 0.9


class _PairRegistrar:
    """Registers pairs of frames from ``load`` on a thread pool; frames prepared for phase
    correlation are kept until both of their pairs are done."""

    def __init__(
        self, load: Callable[[int], Level], params: RegistrationParams, pool: ThreadPoolExecutor
    ) -> None:
        self.load, self.params, self.pool = load, params, pool
        # an image-only guess can be tens of pixels off: search wider, let the refinement travel
        self.blind_params = replace(
            params, search_px=2 * params.search_px, max_refine_px=3 * params.search_px
        )
        self.views: dict[tuple[int, int], PhaseView] = {}

    def measure_blind_guess(
        self, pair: tuple[int, int], start: NDArray[np.float64]
    ) -> PairMeasurement | None:
        """The pair registered from an image-only guess (searching :data:`BLIND_ANGLES`)."""
        return measure_pair(
            self.load, PairRequest(pair[0], pair[1], start, (self.blind_params,), BLIND_ANGLES)
        )

    def _phase_view(self, k: int, scale: int) -> PhaseView:
        view = self.views.get((k, scale))
        if view is None:
            view = self.views[k, scale] = PhaseView.of(self.load(k).half.image, scale, reduced=2)
        return view

    def _blind_guesses(
        self, k: int, previous: PairMeasurement | None
    ) -> Iterator[NDArray[np.float64]]:
        # phase correlation at a quarter of the resolution; then the step of the pair
        # before (a robot moves much as it did a frame earlier); then at half resolution
        for n_scale, scale in enumerate(PHASE_SCALES):
            if n_scale == 1 and previous is not None:
                yield previous.delta
            for g, _ in phase_candidates(
                self._phase_view(k, scale), self._phase_view(k + 1, scale)
            ):
                yield g

    def measure_blind(
        self,
        k: int,
        next_too: bool = False,
        previous: PairMeasurement | None = None,
    ) -> tuple[PairMeasurement | None, NDArray[np.float64]]:
        """Pair (k, k+1) without odometry: guesses verified by registration until one verifies
        surely; frame k+1's preparations are kept when the same thread measures pair k+1 next.
        Returns the best measurement (or None) and the step to use."""
        tried: list[PairMeasurement] = []
        first_guess = None
        for g in self._blind_guesses(k, previous):
            first_guess = g if first_guess is None else first_guess
            m = self.measure_blind_guess((k, k + 1), g)
            if m is not None:
                tried.append(m)
                if m.score > SURE_MATCH:
                    break
        for scale in PHASE_SCALES:
            self.views.pop((k, scale), None)
            if not next_too:
                self.views.pop((k + 1, scale), None)
        if tried:
            best = max(tried, key=lambda m: m.score)
            return best, best.delta
        return None, first_guess if first_guess is not None else np.zeros(3)

    def measure_blind_run(
        self, ks: range
    ) -> list[tuple[PairMeasurement | None, NDArray[np.float64]]]:
        """:meth:`measure_blind` for a run of consecutive pairs, each guided by the one before."""
        out: list[tuple[PairMeasurement | None, NDArray[np.float64]]] = []
        for k in ks:
            out.append(self.measure_blind(k, k + 1 in ks, out[-1][0] if out else None))
        return out


def _consecutive_from_images(
    reg: _PairRegistrar, n: int
) -> tuple[list[PairMeasurement | None], NDArray[np.float64]]:
    """Consecutive pairs measured from the images alone; the step of each pair (its prior)."""
    # each thread takes runs of consecutive pairs: the threads then prepare different
    # frames instead of waiting in turn for the frame the other one is decoding
    blind = [
        r
        for run in reg.pool.map(reg.measure_blind_run, _runs(n - 1, reg.params.workers))
        for r in run
    ]
    consecutive = [m for m, _ in blind]
    steps = [step for _, step in blind]
    # a pair no phase-correlation guess could place (its overlap's texture drowned by
    # something else): a robot moves much as it did a frame earlier or later, so the
    # nearest placed pairs' steps are tried as guesses (and kept as its prior)
    for k in [k for k, m in enumerate(consecutive) if m is None]:
        near = _nearest_measured(consecutive, k)
        for j in near:
            placed = consecutive[j]
            assert placed is not None  # the nearest measured pairs
            found = reg.measure_blind_guess((k, k + 1), placed.delta)
            if found is not None:
                consecutive[k] = found
                break
        if near:
            placed = consecutive[k] if consecutive[k] is not None else consecutive[near[0]]
            assert placed is not None
            steps[k] = placed.delta
    return consecutive, np.array(steps).reshape(-1, 3)


def _consecutive_from_odometry(
    reg: _PairRegistrar, guess: NDArray[np.float64], spread: PairSpread
) -> tuple[list[PairMeasurement | None], NDArray[np.float64]]:
    """Consecutive pairs measured from the odometry's steps (their priors); where the
    odometry was too far off (wheel slip), the images alone decide, within a frame of it."""
    n = len(guess)
    priors = np.array([relative_se2(guess[k], guess[k + 1]) for k in range(n - 1)]).reshape(-1, 3)
    consecutive = spread([PairRequest(k, k + 1, priors[k], (reg.params,)) for k in range(n - 1)])
    lost = [k for k, m in enumerate(consecutive) if m is None]
    h, w = reg.load(0).shape
    corners = np.array(
        [[-w / 2, -h / 2, 1], [w / 2, -h / 2, 1], [w / 2, h / 2, 1], [-w / 2, h / 2, 1]]
    )
    for k, (m, _) in zip(lost, reg.pool.map(reg.measure_blind, lost)):
        # the images alone may pick a look-alike patch anywhere, turned any way: a frame
        # placed more than a frame's length from where the odometry's step puts it is not
        # wheel slip but a false match, and is not kept
        if m is None:
            continue
        moved = corners @ (se2_matrix(*m.delta) - se2_matrix(*priors[k])).T
        if np.max(np.hypot(moved[:, 0], moved[:, 1])) <= max(h, w):
            consecutive[k] = m
    return consecutive, priors


def _other_pairs(
    params: RegistrationParams,
    chained: NDArray[np.float64],
    size: tuple[int, int],
    spread: PairSpread,
) -> list[PairMeasurement | None]:
    """Every other overlapping pair (lane neighbours, revisits), registered from the chain:
    near it first (accurate where consecutive pairs registered), then wider."""
    near = replace(params, search_px=max(8, params.search_px // 3))
    return spread(
        [
            PairRequest(i, j, relative_se2(chained[i], chained[j]), (near, params))
            for i, j in candidate_pairs(chained, size, skip_consecutive=True)
        ]
    )


def _threads_spread(
    load: Callable[[int], Level], pool: ThreadPoolExecutor, workers: int
) -> PairSpread:
    """Pairs registered on ``pool``, each thread taking runs of neighbouring requests (the
    threads then prepare different frames instead of waiting for the same one)."""

    def spread(requests: Sequence[PairRequest]) -> list[PairMeasurement | None]:
        def run(ks: range) -> list[PairMeasurement | None]:
            return [measure_pair(load, requests[k]) for k in ks]

        return [m for found in pool.map(run, _runs(len(requests), workers)) for m in found]

    return spread


def _solve(
    chained: NDArray[np.float64],
    measurements: list[PairMeasurement],
    priors: NDArray[np.float64],
    params: RegistrationParams,
) -> PoseEstimate:
    """The pose graph solved robustly; pairs that still disagree by more than
    ``max_residual_px`` are dropped and the graph solved again."""
    n = len(chained)
    poses = solve_pose_graph(chained, measurements, priors, params)
    res = measurement_residuals(poses, measurements, params)
    keep = [m for m, r in zip(measurements, res) if r <= params.max_residual_px]
    rejected = len(measurements) - len(keep)
    if rejected:
        poses = solve_pose_graph(poses, keep, priors, params)
    confident = np.zeros(n, bool)
    confident[0] = n == 1
    for m in keep:
        confident[[m.i, m.j]] = True
    return PoseEstimate(poses, confident, keep, rejected)


def estimate_poses(
    load: Callable[[int], Level],
    n: int,
    guess: NDArray[np.float64] | None,
    params: RegistrationParams = RegistrationParams(),
    progress: Callable[[float, str], None] | None = None,
    spread: PairSpread | None = None,
) -> PoseEstimate:
    """Globally consistent frame poses from images (and an odometry guess when given).

    1. initial steps: odometry, or phase correlation between consecutive frames;
    2. every consecutive pair registered (sub-pixel), the steps chained;
    3. every other overlapping pair (lane neighbours, revisits) registered from the chain;
    4. the pose graph solved robustly; pairs that still disagree by more than
       ``max_residual_px`` are dropped and the graph solved again.
    Frames that no accepted pair reaches keep their odometry placement and are flagged.
    ``load(k)`` gives frame k's grey levels; it is called from ``params.workers`` threads.
    ``spread`` registers the pairs of steps 2 and 3 elsewhere (default: those threads).
    """
    report = progress or (lambda f, m: None)
    if n == 0:
        raise ValueError("no frames")
    h, w = load(0).shape
    with ThreadPoolExecutor(max(1, params.workers)) as pool:
        reg = _PairRegistrar(load, params, pool)
        pairs = spread or _threads_spread(load, pool, params.workers)
        report(0.05, "registering consecutive frames")
        if guess is None:
            consecutive, priors = _consecutive_from_images(reg, n)
            guess = chain_se2(np.zeros(3), list(priors))
        else:
            guess = np.asarray(guess, dtype=np.float64)
            consecutive, priors = _consecutive_from_odometry(reg, guess, pairs)
        chained = chain_se2(
            guess[0], [m.delta if m is not None else priors[k] for k, m in enumerate(consecutive)]
        )
        report(0.4, "registering overlapping frames")
        others = _other_pairs(params, chained, (w, h), pairs)
    report(0.8, "solving the pose graph")
    return _solve(chained, [m for m in consecutive + others if m is not None], priors, params)
