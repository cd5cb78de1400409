"""The robot's wheels: a climbing robot rolls, it does not slide sideways.

A wheeled robot on a plate moves each step along an arc about a point on its axle's line
(a non-holonomic constraint): every point of that line moves straight ahead, never across.
The ToF camera is fixed on the robot, so its own motion obeys the same law seen from where
it sits. With the robot's up, forward and left axes (n, f, l) in the sensor frame and the
sensor ``a`` ahead of the axle's line, a step that turns the heading by θ about n moves
the sensor by D (its (f, l) components) with

    r = w(θ/2) · D − 2·a·sin(θ/2) = 0,    w(α) = (−sin α, cos α),

whatever the distance driven (where the sensor sits across the robot does not enter: the
whole axle line moves ahead). That holds the distance along a member in a turn, where the
view sees only planes parallel to the member but the heading and the motion across it are
fixed (:mod:`processing.mapping.tracking`): the arc ties the one to the others.

Nothing here is configured: the axes and ``a`` are fitted to the trajectory the map has
(:func:`fit_wheel_model`), and how well the law holds (the robot rocks, its wheels slip)
is the residuals' robust spread. A trajectory without turns, or one the law does not fit
better than half the odometry's own error, gets no model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class WheelModel:
    """The robot's axes in the sensor frame (unit (3,) each), how far the sensor is ahead
    of the axle's line (m; negative: behind) and the spread of the law's residual (m)."""

    up: NDArray[np.float64]
    forward: NDArray[np.float64]
    left: NDArray[np.float64]
    ahead_m: float
    sigma_m: float


def _terms(
    steps: NDArray[np.float64], forward: NDArray[np.float64], left: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """For relative poses ``steps`` (K, 4, 4) and robot axes ``forward``, ``left`` ((3,), or
    (P, 3) for P candidate axes): each step's heading change θ (K,) or (P, K), the law's
    direction w(θ/2) (..., K, 2) and the sensor's planar motion D (..., K, 2)."""
    turned = np.einsum("kij,...j->...ki", steps[:, :3, :3], forward)
    theta = np.arctan2(
        np.einsum("...ki,...i->...k", turned, left), np.einsum("...ki,...i->...k", turned, forward)
    )
    w = np.stack([-np.sin(theta / 2), np.cos(theta / 2)], axis=-1)
    t = steps[:, :3, 3]
    D = np.stack([np.einsum("ki,...i->...k", t, forward), np.einsum("ki,...i->...k", t, left)], -1)
    return theta, w, D


def residuals(model: WheelModel, steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """The law's residual r (K,) for relative poses ``steps`` (K, 4, 4), T_prev_next (m)."""
    theta, w, D = _terms(steps, model.forward, model.left)
    return np.einsum("ij,ij->i", w, D) - 2 * np.sin(theta / 2) * model.ahead_m


def _fit_ahead(
    theta: NDArray[np.float64], w: NDArray[np.float64], D: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``a`` by iteratively reweighted least squares (Cauchy weights at the residuals'
    robust spread), and the residuals (..., K); for P candidate axes at once with a leading
    axis P (``a``: (P,))."""
    lever, b = 2 * np.sin(theta / 2), np.einsum("...j,...j->...", w, D)
    weights = np.ones_like(b)
    ahead = np.zeros(b.shape[:-1])
    for _ in range(5):
        ahead = np.sum(weights * lever * b, -1) / np.maximum(np.sum(weights * lever**2, -1), 1e-12)
        r = b - lever * ahead[..., None]
        scale = np.maximum(1.4826 * np.median(np.abs(r), axis=-1), 1e-6)
        weights = 1 / (1 + (r / scale[..., None]) ** 2)
    return ahead, b - lever * ahead[..., None]


def fit_wheel_model(poses: NDArray[np.float64], odometry_sigma_m: float) -> WheelModel | None:
    """The wheel model that best explains the trajectory ``poses`` (N, 4, 4), or None where
    the robot did not turn or the law fits no better than half the odometry's error per
    step (``odometry_sigma_m``: then it would add nothing)."""
    if len(poses) < 8:
        return None
    steps = np.linalg.inv(poses[:-1]) @ poses[1:]
    rotvecs = Rotation.from_matrix(steps[:, :3, :3]).as_rotvec()
    values, vectors = np.linalg.eigh(rotvecs.T @ rotvecs)
    # the heading turns about the plate's normal, the rocking about any axis: without turns
    # (two thirds of the rotation about one axis) the plate's normal is unknown
    if values[2] < 2 * (values[0] + values[1]):
        return None
    up = vectors[:, 2]
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)

    def spreads(phis: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        forward = np.cos(phis)[:, None] * e1 + np.sin(phis)[:, None] * e2  # (P, 3)
        ahead, r = _fit_ahead(*_terms(steps, forward, np.cross(up, forward)))
        return np.median(np.abs(r), axis=-1), ahead, forward

    # forward and backward are one model: half a turn of candidates, then finer about the best
    coarse = np.linspace(0, np.pi, 180, endpoint=False)
    best = coarse[np.argmin(spreads(coarse)[0])]
    mads, aheads, forwards = spreads(best + np.linspace(-np.pi / 180, np.pi / 180, 21))
    k = int(np.argmin(mads))
    mad, ahead, forward = float(mads[k]), float(aheads[k]), forwards[k]
    sigma = 1.4826 * mad
    if sigma >= odometry_sigma_m / 2:
        return None
    return WheelModel(up, forward, np.cross(up, forward), ahead, sigma)


def wheel_edge(
    model: WheelModel, step: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A pose-graph edge for one step (``step``: T_prev_next (4, 4), the current estimate):
    the step moved across the arc so the law holds, and its information (6, 6; rotation
    first, in the next pose's frame, where the graph measures an edge's error): the law's
    direction alone, at the model's spread."""
    _, w, _ = _terms(step[None], model.forward, model.left)
    r = float(residuals(model, step[None])[0])
    across = w[0, 0] * model.forward + w[0, 1] * model.left  # ∂r/∂t, in the previous frame
    measured = step.copy()
    measured[:3, 3] -= r * across
    across_next = step[:3, :3].T @ across
    information = np.zeros((6, 6))
    information[3:, 3:] = np.outer(across_next, across_next) / model.sigma_m**2
    return measured, information
