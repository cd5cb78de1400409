"""The least trajectory error any map could reach on a simulated sequence: the Cramér–Rao
bound of the sensor poses given every range the ToF measured *against the true structure*
(as if the map were known beforehand, which no mapper has) and the odometry's steps with
their error model.

Each return of cloud i constrains its pose only along the normal of the surface it hits:
with a world-frame perturbation ξ = (ω, v) of the pose, the range along the ray changes by
-(q × n · ω + n · v) / (n · d) (q the point, n the surface's normal, d the ray), so its
Fisher information is [q × n, n]ᵀ[q × n, n] / (σ (n · d))² for range noise σ along the
ray. A plate parallel to the route says nothing about the distance along it, however
many points it returns; only the faces across the route (stiffeners, plates, bolt heads)
do. Each odometry step adds its error model's information on the relative pose
(Ad(T_k⁻¹)(ξ_k - ξ_(k-1)), 6-DoF σ per step), and the wheels add what a robot that does
not slide sideways knows for certain: each step runs along the mean of its two headings
(the chord of the arc it drives; :mod:`processing.mapping.wheels` uses it), which ties the
distance along a member to the motion across it wherever the heading turns away from the
member, and says nothing about it on a straight lane. The inverse of the summed information is
the least covariance of the poses; the bound on the trajectory error (TUM ATE: RMS of the
positions after a rigid alignment, which removes any error common to the whole
trajectory) is its positions' share outside the rigid motions.

The downward camera adds, for each pair of consecutive clouds, the footprint step its
frames measure (:mod:`processing.mapping.camera_motion`): where the later camera's optical
axis meets the surface in the earlier camera's frame, and the turn about the normal, each
registered to ``sigma_px`` and scaled by the distance to the surface, so its information
is Jᵀ Σ⁻¹ J with J the step's derivative with respect to both poses.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from processing.mapping.camera_motion import foot
from processing.poses import se3_adjoint_inverse, se3_exp, skew, wrap_angle
from robot_link.sim.sensors import TofCamera

MIN_INCIDENCE = 0.05  # |n·d| floor: returns at grazing incidence count as if at this angle
NO_SLIP_M = 1e-4  # the wheels' constraint, as good as exact (the simulated robot never slips)
WEAK_PRIOR = 10.0  # m and rad: what fixes the whole trajectory where nothing else does


def view_information(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    dirs: NDArray[np.float64],
    sigma_m: float,
) -> NDArray[np.float64]:
    """Fisher information (6, 6) of one pose (world-frame (ω, v)) from the true surface its
    pixels hit: ``points``, ``normals``, ray ``dirs`` (K, 3) each, range noise ``sigma_m``."""
    J = np.hstack([np.cross(points, normals), normals])
    incidence = np.maximum(np.abs(np.sum(normals * dirs, axis=1)), MIN_INCIDENCE)
    w = 1.0 / (sigma_m * incidence) ** 2
    return (J * w[:, None]).T @ J


def pose_information(
    infos: list[NDArray[np.float64]],
    truth: NDArray[np.float64],
    odometry_sigmas: tuple[float, float],
) -> NDArray[np.float64]:
    """The information (6N, 6N) of N poses ``truth`` (N, 4, 4): each view's (``infos``) and
    each odometry step's (σ rotation rad, translation m per axis, in the later pose's frame)."""
    n = len(truth)
    H = np.zeros((6 * n, 6 * n))
    for i, info in enumerate(infos):
        H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += info
    rot, trans = odometry_sigmas
    Lam = np.diag([rot**-2] * 3 + [trans**-2] * 3)
    for k in range(1, n):
        A = se3_adjoint_inverse(truth[k])
        E = A.T @ Lam @ A  # residual A (ξ_k - ξ_(k-1))
        a, b = slice(6 * (k - 1), 6 * k), slice(6 * k, 6 * k + 6)
        H[a, a] += E
        H[b, b] += E
        H[a, b] -= E
        H[b, a] -= E
    return H + np.eye(6 * n) / WEAK_PRIOR**2


def _point_jacobian(p: NDArray[np.float64]) -> NDArray[np.float64]:
    """(3, 6): how a point p fixed to a pose moves with the pose's world-frame (ω, v)."""
    return np.hstack([-skew(p), np.eye(3)])


def no_slip_information(
    truth: NDArray[np.float64], T_robot_sensor: NDArray[np.float64], sigma_m: float = NO_SLIP_M
) -> NDArray[np.float64]:
    """The information (6N, 6N) on the sensor poses ``truth`` (N, 4, 4) of a robot carrying
    the sensor at ``T_robot_sensor`` whose every step runs along the mean of its headings:
    the step's sideways part c = n · (r_k - r_(k-1)) is zero (r the robot's origin, n across
    the mean heading ψ̄), δc = n · (δr_k - δr_(k-1)) - L (δψ_(k-1) + δψ_k) / 2 for a step of
    length L."""
    n_poses = len(truth)
    robot = truth @ np.linalg.inv(T_robot_sensor)
    r, heading = robot[:, :3, 3], np.arctan2(robot[:, 1, 0], robot[:, 0, 0])
    H = np.zeros((6 * n_poses, 6 * n_poses))
    for k in range(1, n_poses):
        mean = heading[k - 1] + np.angle(np.exp(1j * (heading[k] - heading[k - 1]))) / 2
        along = np.array([np.cos(mean), np.sin(mean), 0.0])
        across = np.array([-np.sin(mean), np.cos(mean), 0.0])
        length = float(along @ (r[k] - r[k - 1]))
        J = np.zeros(12)
        J[:6] = -across @ _point_jacobian(r[k - 1])
        J[6:] = across @ _point_jacobian(r[k])
        J[2] -= length / 2  # δψ is the yaw part of ω
        J[8] -= length / 2
        H[6 * (k - 1) : 6 * (k + 1), 6 * (k - 1) : 6 * (k + 1)] += np.outer(J, J) / sigma_m**2
    return H


def camera_information(
    truth: NDArray[np.float64],
    T_tof_camera: NDArray[np.float64],
    distance_m: float,
    f_px: float,
    size: tuple[int, int],
    sigma_px: float,
    pairs_per_step: float = 1.0,
) -> NDArray[np.float64]:
    """The information (6N, 6N) on the sensor poses ``truth`` (N, 4, 4) of a downward
    camera at ``T_tof_camera`` (focal length ``f_px``, image ``size`` (w, h) px),
    ``distance_m`` from the surface, whose consecutive frames are registered to
    ``sigma_px``, ``pairs_per_step`` frame pairs chained between two poses: each step's
    foot and turn, σ = sigma_px · distance / f in metres and sigma_px over the image's
    half-diagonal in radians, for each pair."""
    n = len(truth)
    sigma_m = sigma_px * distance_m / f_px
    sigma_turn = sigma_px / (0.5 * float(np.hypot(*size)))
    info = np.diag([sigma_m**-2, sigma_m**-2, sigma_turn**-2]) / max(pairs_per_step, 1.0)
    H = np.zeros((6 * n, 6 * n))
    h = 1e-6

    def step(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        return foot(np.linalg.inv(a @ T_tof_camera) @ b @ T_tof_camera, distance_m)

    for k in range(1, n):
        m0 = step(truth[k - 1], truth[k])
        J = np.zeros((3, 12))
        for j in range(12):
            xi = np.zeros(6)
            xi[j % 6] = h
            a, b = truth[k - 1], truth[k]
            if j < 6:
                a = se3_exp(xi) @ a  # world-frame (ω, v), as the views' information
            else:
                b = se3_exp(xi) @ b
            dm = step(a, b) - m0
            dm[2] = float(wrap_angle(dm[2]))
            J[:, j] = dm / h
        H[6 * (k - 1) : 6 * (k + 1), 6 * (k - 1) : 6 * (k + 1)] += J.T @ info @ J
    return H


def aligned_error_bound(H: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """Least RMS position error (m) after rigid alignment, from the information ``H`` of the
    poses ``truth`` (N, 4, 4): the root of the mean expected squared error of an unbiased
    estimate."""
    n = len(truth)
    t = truth[:, :3, 3]
    # positions' error from the poses' (ω, v): δt_i = ω_i × t_i + v_i
    P = np.zeros((3 * n, 6 * n))
    for i in range(n):
        P[3 * i : 3 * i + 3, 6 * i : 6 * i + 6] = _point_jacobian(t[i])
    cov = P @ np.linalg.solve(H, P.T)
    # the rigid motions of the whole trajectory, which the alignment takes out
    rigid = np.vstack([_point_jacobian(p) for p in t])
    Q = np.eye(3 * n) - rigid @ np.linalg.pinv(rigid)
    return float(np.sqrt(np.trace(Q @ cov @ Q) / n))


def trajectory_bound(
    camera: TofCamera,
    truth: NDArray[np.float64],
    odometry_sigmas: tuple[float, float],
    down: NDArray[np.float64] | None = None,
) -> float:
    """Least ATE (m) of any map of ``camera``'s views from the poses ``truth`` (N, 4, 4)
    with odometry of ``odometry_sigmas`` (rad, m per axis and step), on a robot that does
    not slide sideways; with ``down`` (the information of a downward camera,
    :func:`camera_information`) beside them."""
    infos = [view_information(*camera.surface(T), camera.noise_sigma_m) for T in truth]
    H = pose_information(infos, truth, odometry_sigmas)
    H = H + no_slip_information(truth, camera.T_robot_tof)
    return aligned_error_bound(H if down is None else H + down, truth)
