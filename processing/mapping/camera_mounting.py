"""The downward camera's mounting checked against the ToF's own motion (hand-eye).

A camera step and the ToF step between the same two clouds are one motion seen through
the camera's mounting ``T_tof_camera``: the ToF's relative pose A carried into the camera's
frame, X = T_tc⁻¹ A T_tc, has the footprint step :func:`~.camera_motion.foot` that the
frames measured. A mounting off by ξ (a twist in the camera's frame, T_tc exp(ξ)) shows in
that agreement: a lever arm off by δ moves every turning step's foot by (R(ψ) − I) δ, and a
turn about the optical axis turns every step. A tilt θ moves the foot by the camera's
height times θ, as a lever arm of that length does, so the lever stands for it: ξ = (0, 0,
ωz, vx, vy, 0). The length of the steps is not checked: their scale is the surface distance
the ToF measures, and where the ToF's own steps are least sure of their length (along a
uniform member) is where the map needs the camera's. The mounting's error is the ξ that
best makes the two agree (Gauss-Newton with Huber weights on the residuals, their scale
measured from the residuals themselves, and a prior of a mounting known to centimetres and
degrees), and it is real when it explains the steps significantly better than the stated
mounting does (a likelihood-ratio test) on the whole route and on each half of it. Then the
camera's steps are taken through the corrected mounting; otherwise they stay as stated.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import FootStep, foot
from processing.poses import se3_exp, wrap_angle


@dataclass(frozen=True)
class MountingParams:
    """How the mounting is checked (``enabled`` False: the stated mounting is taken)."""

    enabled: bool = True
    prior_rad: float = 0.05  # the stated mounting's rotations are known to a few degrees
    prior_m: float = 0.03  # and its position to a few centimetres
    huber: float = 2.0  # residuals beyond this many robust deviations count linearly
    # the likelihood ratio at which the stated mounting is rejected (χ², 3 dof, p ≈ 1e-6)
    test_statistic: float = 27.9
    # and each half of the route's steps on its own at this (χ², 3 dof, p ≈ 0.01)
    half_statistic: float = 11.3
    min_steps: int = 20  # steps seen by both sensors, at least, for any check
    iterations: int = 8


@dataclass(frozen=True)
class MountingFit:
    """The mounting's correction ξ (6,: ω rad then v m, in the camera's frame) with its
    standard deviations, the likelihood ratio of the corrected against the stated mounting,
    the steps both sensors saw, the robust residual scale (translation m, heading rad) and
    whether the correction is taken."""

    xi: NDArray[np.float64]
    std: NDArray[np.float64]
    statistic: float
    steps: int
    scale: tuple[float, float]
    corrected: bool
    halves: tuple[float, ...] = ()  # the likelihood ratio of each half of the route alone

    def summary(self) -> dict[str, object]:
        """JSON-ready: the correction in mm and degrees, the test and the decision."""
        return {
            "corrected": self.corrected,
            "rotation_deg": [round(float(np.degrees(v)), 3) for v in self.xi[:3]],
            "translation_mm": [round(1000 * float(v), 2) for v in self.xi[3:]],
            "translation_std_mm": [round(1000 * float(v), 2) for v in self.std[3:]],
            "likelihood_ratio": round(self.statistic, 1),
            "likelihood_ratio_halves": [round(v, 1) for v in self.halves],
            "steps": self.steps,
        }


def _residuals(
    xi: NDArray[np.float64],
    measured: NDArray[np.float64],
    tof: NDArray[np.float64],
    distances: NDArray[np.float64],
    T_tc: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(n, 3) camera step minus the ToF step seen through the mounting T_tc exp(ξ)
    (``measured`` (n, 3), ``tof`` (n, 4, 4), ``distances`` (n,)): a camera moved along its
    axis is that much nearer the surface, and its pixels' scale with it."""
    T = T_tc @ se3_exp(xi)
    z_new = distances - float(xi[5])
    predicted = foot(np.linalg.inv(T) @ tof @ T, z_new)
    k = (z_new / distances)[:, None]
    r = np.column_stack([measured[:, :2] * k, measured[:, 2]]) - predicted
    r[:, 2] = wrap_angle(r[:, 2])
    return r


def _huber(e: NDArray[np.float64], k: float) -> NDArray[np.float64]:
    """ρ of each normalised residual (½e² within k, linear beyond)."""
    a = np.abs(e)
    return np.where(a <= k, 0.5 * a**2, k * a - 0.5 * k**2)


def _fit(
    measured: NDArray[np.float64],
    A: NDArray[np.float64],
    z: NDArray[np.float64],
    T_tc: NDArray[np.float64],
    params: MountingParams,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, NDArray[np.float64]]:
    """ξ, its standard deviations, the likelihood ratio against ξ = 0 and the residuals'
    robust scale (translation, translation, heading) of the steps (``measured`` (n, 3), ToF
    ``A`` (n, 4, 4), distances ``z`` (n,))."""
    prior = np.array([params.prior_rad] + [params.prior_m] * 2)

    def scale_of(r: NDArray[np.float64]) -> NDArray[np.float64]:
        """Robust deviation of the translation residuals (both axes) and the heading's."""
        t = 1.4826 * float(np.median(np.abs(r[:, :2] - np.median(r[:, :2], axis=0))))
        h = 1.4826 * float(np.median(np.abs(r[:, 2] - np.median(r[:, 2]))))
        return np.array([max(t, 1e-5), max(t, 1e-5), max(h, 1e-6)])

    def residuals(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return _residuals(np.r_[0.0, 0.0, p, 0.0], measured, A, z, T_tc)

    def objective(p: NDArray[np.float64], s: NDArray[np.float64]) -> float:
        e = residuals(p) / s
        return float(_huber(e, params.huber).sum() + 0.5 * np.sum((p / prior) ** 2))

    xi = np.zeros(3)
    r = residuals(xi)
    s = scale_of(r)
    H = np.diag(1 / prior**2)
    for _ in range(params.iterations):
        e = r / s
        w = np.where(np.abs(e) <= params.huber, 1.0, params.huber / np.maximum(np.abs(e), 1e-12))
        J = np.empty((len(measured), 3, 3))
        for j in range(3):
            h = np.zeros(3)
            h[j] = 1e-6
            dr = residuals(xi + h) - r
            dr[:, 2] = wrap_angle(dr[:, 2])
            J[:, :, j] = dr / 1e-6
        Jn = J / s[None, :, None]
        H = np.einsum("nai,na,naj->ij", Jn, w, Jn) + np.diag(1 / prior**2)
        g = np.einsum("nai,na,na->i", Jn, w, e) + xi / prior**2
        step = -np.linalg.solve(H, g)
        xi = xi + step
        r = residuals(xi)
        s = scale_of(r)
        if np.max(np.abs(step) / prior) < 1e-4:
            break
    statistic = 2 * (objective(np.zeros(3), s) - objective(xi, s))
    std = np.sqrt(np.diag(np.linalg.inv(H)))
    return np.r_[0.0, 0.0, xi, 0.0], np.r_[0.0, 0.0, std, 0.0], float(statistic), s


def fit_mounting(
    camera_steps: Sequence[FootStep | None],
    tof_steps: NDArray[np.floating],
    distances_m: NDArray[np.floating],
    T_tof_camera: NDArray[np.floating],
    usable: NDArray[np.bool_] | None = None,
    params: MountingParams = MountingParams(),
) -> MountingFit | None:
    """The mounting's correction from the steps between consecutive clouds: the camera's
    ``camera_steps`` (N - 1; None where the frames do not link them), the ToF's relative
    poses ``tof_steps`` ((N - 1, 4, 4), ToF frame), the surface distance at each step's
    first cloud ``distances_m`` (N - 1) and the stated mounting ``T_tof_camera`` (4, 4);
    ``usable`` (N - 1) marks the ToF steps that registration fixed. None when fewer than
    ``params.min_steps`` steps are seen by both.

    The correction is taken when it explains all the steps significantly better than the
    stated mounting and each half of the route on its own shows it too (a stretch where
    the ToF itself slipped shows in one half only)."""
    tof = np.asarray(tof_steps, np.float64)
    z = np.asarray(distances_m, np.float64)
    n = len(camera_steps)
    if len(tof) != n or len(z) != n or (usable is not None and len(usable) != n):
        raise ValueError(
            f"one ToF step, distance and usable flag per camera step: {n} camera steps, "
            f"{len(tof)} ToF steps, {len(z)} distances"
            + ("" if usable is None else f", {len(usable)} flags")
        )
    pairs = [
        (k, step)
        for k, step in enumerate(camera_steps)
        if step is not None and np.isfinite(z[k]) and (usable is None or bool(usable[k]))
    ]
    # each half of the route is tested on its own: two steps at least in each
    if len(pairs) < max(params.min_steps, 4):
        return None
    keep = [k for k, _ in pairs]
    measured = np.array([step.delta for _, step in pairs])
    A, zk = tof[keep], z[keep]
    T_tc = np.asarray(T_tof_camera, np.float64)
    xi, std, statistic, s = _fit(measured, A, zk, T_tc, params)
    # split by time: a half without turns cannot show a lever arm, and the correction is
    # then refused (the check errs towards the stated mounting)
    half = len(keep) // 2
    halves = [
        _fit(measured[part], A[part], zk[part], T_tc, params)[2]
        for part in (slice(0, half), slice(half, None))
    ]
    corrected = statistic > params.test_statistic and min(halves) > params.half_statistic
    return MountingFit(
        xi, std, statistic, len(keep), (float(s[0]), float(s[2])), corrected, tuple(halves)
    )
