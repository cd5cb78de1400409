"""The frames' 2D pose graph: which pairs may overlap, and all poses solved together
(robust Gauss–Newton) so that error does not accumulate along the robot's path."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import spsolve

from processing.poses import relative_se2, wrap_angle
from processing.stitching.registration import PairMeasurement, RegistrationParams


def candidate_pairs(
    poses: NDArray[np.float64], size: tuple[int, int], *, skip_consecutive: bool = False
) -> list[tuple[int, int]]:
    """Pairs (i < j) of frames whose centres are close enough for their footprints to overlap
    (the overlap itself is checked when the pair is registered)."""
    reach = 0.9 * max(size)
    out = []
    centres = poses[:, :2]
    order = np.argsort(centres[:, 0])
    xs = centres[order, 0]
    for a, i in enumerate(order):
        hi = np.searchsorted(xs, xs[a] + reach, side="right")
        for j in order[a + 1 : hi]:
            if np.linalg.norm(centres[j] - centres[i]) < reach:
                p = (int(min(i, j)), int(max(i, j)))
                if not (skip_consecutive and p[1] == p[0] + 1):
                    out.append(p)
    return sorted(out, key=lambda p: (p[1], p[0]))


def solve_pose_graph(
    initial: NDArray[np.float64],
    measurements: Sequence[PairMeasurement],
    priors: NDArray[np.float64] | None,
    params: RegistrationParams = RegistrationParams(),
    *,
    iterations: int = 10,
) -> NDArray[np.float64]:
    """Poses (N, 3) minimising the robust pose-graph error (Gauss-Newton with Huber weights).

    Each measurement says where frame j is in frame i's frame; ``priors`` (N-1, 3), the
    odometry's relative steps, weakly hold frames that no image measurement reaches.
    Frame 0 stays where ``initial`` puts it (the gauge).
    """
    n = len(initial)
    edges = [(m.i, m.j, m.delta, 1.0) for m in measurements]
    if priors is not None:
        edges += [(k, k + 1, priors[k], params.prior_weight) for k in range(n - 1)]
    if n < 2 or not edges:
        return initial.copy()
    I = np.array([e[0] for e in edges])
    J = np.array([e[1] for e in edges])
    Z = np.array([e[2] for e in edges], float)
    base_w = np.array([e[3] for e in edges], float)
    x = initial.astype(np.float64).copy()
    L = params.lever_px
    for _ in range(iterations):
        ti, tj, th = x[I, :2], x[J, :2], x[I, 2]
        c, s = np.cos(th), np.sin(th)
        d = tj - ti
        pred = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        r = np.column_stack([pred - Z[:, :2], L * wrap_angle(x[J, 2] - th - Z[:, 2])])
        norm = np.linalg.norm(r, axis=1)
        w = base_w * np.where(
            norm <= params.huber_px, 1.0, params.huber_px / np.maximum(norm, 1e-12)
        )
        Jm = _jacobian(I, J, c, s, d, L, n)
        Wd = sp.diags(np.repeat(w, 3))
        H = (Jm.T @ Wd @ Jm).tocsc()[3:, 3:]  # frame 0 fixed
        g = (Jm.T @ (np.repeat(w, 3) * r.ravel()))[3:]
        H = H + sp.identity(H.shape[0], format="csc") * 1e-9
        step = spsolve(H, -g)
        x[1:] += step.reshape(n - 1, 3)
        x[:, 2] = wrap_angle(x[:, 2])
        if np.abs(step).max() < 1e-4:
            break
    return x


def _jacobian(
    I: NDArray[np.int_],
    J: NDArray[np.int_],
    c: NDArray[np.float64],
    s: NDArray[np.float64],
    d: NDArray[np.float64],
    L: float,
    n: int,
) -> sp.csr_matrix:
    """The residuals' Jacobian (3E, 3N): rows 3e..3e+2 of edge e (from pose ``I[e]`` to
    pose ``J[e]``, cos and sin of pose i's heading ``c``, ``s``, their offset ``d``, the
    heading's lever ``L``), columns of pose i and pose j."""
    ne = len(I)
    one = np.ones(ne)
    blocks = [  # (residual row, node, pose component, derivative)
        (0, I, 0, -c),
        (0, I, 1, -s),
        (0, I, 2, -s * d[:, 0] + c * d[:, 1]),
        (1, I, 0, s),
        (1, I, 1, -c),
        (1, I, 2, -c * d[:, 0] - s * d[:, 1]),
        (2, I, 2, -L * one),
        (0, J, 0, c),
        (0, J, 1, s),
        (1, J, 0, -s),
        (1, J, 1, c),
        (2, J, 2, L * one),
    ]
    e = np.arange(ne)
    rows = np.concatenate([3 * e + r for r, _, _, _ in blocks])
    cols = np.concatenate([3 * node + k for _, node, k, _ in blocks])
    vals = np.concatenate([v for _, _, _, v in blocks])
    return sp.csr_matrix((vals, (rows, cols)), shape=(3 * ne, 3 * n))


def measurement_residuals(
    poses: NDArray[np.float64], measurements: Sequence[PairMeasurement], params: RegistrationParams
) -> NDArray[np.float64]:
    """Size (px) of each measurement's disagreement with the poses."""
    out = []
    for m in measurements:
        r = relative_se2(poses[m.i], poses[m.j]) - m.delta
        out.append(float(np.hypot(r[0], r[1]) + params.lever_px * abs(float(wrap_angle(r[2])))))
    return np.array(out)
