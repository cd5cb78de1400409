"""Robust pose-graph optimisation with a sparse linear system.

The same optimisation as Open3D's ``global_optimization`` with Levenberg-Marquardt (Choi,
Zhou and Koltun, "Robust reconstruction of indoor scenes", CVPR 2015): every edge's
misalignment ζ (eq. (6) there, linearised SE(3): half the skew part of the rotation and
the translation), weighted by its information matrix; uncertain edges (loop closures,
plane sightings) carry a line process l = (μ / (μ + ζᵀΛζ))² with μ the line-process
weight (eq. (2), Section 5), so an edge that disagrees with the rest fades out; then the
edges whose l fell below the prune threshold are dropped and the graph optimised again,
twice, and the reference node is put back where it was.

Open3D assembles the normal equations as a dense 6N × 6N matrix, which costs O(N²)
memory and O(N³) time a solve: a 400-cloud session spent seconds per optimisation there,
and a 2,000-cloud one would not finish. Here every edge adds four 6 × 6 blocks to a
sparse matrix (a pose graph's edges tie each cloud to a few others) and the system is
solved by sparse LU, so an optimisation costs about linear time in the clouds and edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

reg = o3d.pipelines.registration

# up to this many nodes Open3D's own optimiser (a dense system) is faster than the sparse one
DENSE_UP_TO = 150

# the generators of the linearised SE(3) (rotations about x, y, z, then translations)
_GENERATORS = np.zeros((6, 4, 4))
_GENERATORS[0, 1, 2], _GENERATORS[0, 2, 1] = -1, 1
_GENERATORS[1, 0, 2], _GENERATORS[1, 2, 0] = 1, -1
_GENERATORS[2, 0, 1], _GENERATORS[2, 1, 0] = -1, 1
_GENERATORS[3, 0, 3] = _GENERATORS[4, 1, 3] = _GENERATORS[5, 2, 3] = 1


@dataclass(frozen=True)
class GraphOptions:
    """The optimisation's options and stopping rules (Open3D's defaults)."""

    max_correspondence_m: float = 0.075  # sets the line-process weight with ``preference``
    edge_prune_threshold: float = 0.25
    preference: float = 1.0
    reference_node: int = 0  # this node keeps its pose
    max_iterations: int = 100
    max_iterations_lm: int = 20
    min_relative_increment: float = 1e-6
    min_relative_residual_increment: float = 1e-6
    min_right_term: float = 1e-6
    min_residual: float = 1e-30
    upper_scale_factor: float = 2.0 / 3.0
    lower_scale_factor: float = 1.0 / 3.0


@dataclass
class PoseGraphArrays:
    """A pose graph as arrays: node poses (N, 4, 4); edges (E) from ``source`` to
    ``target`` measuring T_target_source ``transformation`` (E, 4, 4) with ``information``
    (E, 6, 6; rotation first), ``uncertain`` (E,) and their line process ``confidence``
    (E,)."""

    poses: NDArray[np.float64]
    source: NDArray[np.int64]
    target: NDArray[np.int64]
    transformation: NDArray[np.float64]
    information: NDArray[np.float64]
    uncertain: NDArray[np.bool_]
    confidence: NDArray[np.float64]

    def edges_where(self, keep: NDArray[np.bool_]) -> PoseGraphArrays:
        """The same nodes with only the edges ``keep`` (E,) selects."""
        return PoseGraphArrays(
            self.poses,
            self.source[keep],
            self.target[keep],
            self.transformation[keep],
            self.information[keep],
            self.uncertain[keep],
            self.confidence[keep],
        )


def _linearised(M: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 6-vectors (..., 6) of near-identity transforms M (..., 4, 4)."""
    return np.stack(
        [
            (M[..., 2, 1] - M[..., 1, 2]) / 2,
            (M[..., 0, 2] - M[..., 2, 0]) / 2,
            (M[..., 1, 0] - M[..., 0, 1]) / 2,
            M[..., 0, 3],
            M[..., 1, 3],
            M[..., 2, 3],
        ],
        axis=-1,
    )


def _rigid_inverse(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverses of rigid transforms T (..., 4, 4)."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _misalignment(
    g: PoseGraphArrays, X_inv: NDArray[np.float64], poses: NDArray[np.float64]
) -> NDArray[np.float64]:
    """ζ (E, 6): each edge's measurement (inverted: ``X_inv``) against the poses, linearised."""
    return _linearised(X_inv @ _rigid_inverse(poses)[g.target] @ poses[g.source])


def _line_process_weight(g: PoseGraphArrays, options: GraphOptions) -> float:
    """μ: the preference times the squared correspondence distance times the edges' mean
    number of correspondences (the information's last diagonal entry)."""
    if len(g.source) == 0:
        return 0.0
    return float(
        options.preference * options.max_correspondence_m**2 * g.information[:, 5, 5].mean()
    )


def _confidence(g: PoseGraphArrays, zeta: NDArray[np.float64], mu: float) -> NDArray[np.float64]:
    """The line process of every edge: (μ / (μ + ζᵀΛζ))² where uncertain, else as it is."""
    chi2 = np.einsum("ei,eij,ej->e", zeta, g.information, zeta)
    return np.where(g.uncertain, (mu / (mu + chi2)) ** 2, g.confidence)


def _residual(
    g: PoseGraphArrays, zeta: NDArray[np.float64], confidence: NDArray[np.float64], mu: float
) -> float:
    """Σ l ζᵀΛζ + μ (√l − 1)² (eq. (9) of Choi et al.)."""
    chi2 = np.einsum("ei,eij,ej->e", zeta, g.information, zeta)
    return float(np.sum(confidence * chi2 + mu * (np.sqrt(confidence) - 1) ** 2))


class _Pattern:
    """Where every edge's four 6 × 6 blocks (and the diagonal) fall in the compressed
    columns of the 6N × 6N normal matrix: computed once per optimisation, so each
    iteration only sums the blocks' values into place."""

    def __init__(self, source: NDArray[np.int64], target: NDArray[np.int64], n: int) -> None:
        idx = np.arange(6)
        self.s6 = (source * 6)[:, None] + idx  # (E, 6)
        self.t6 = (target * 6)[:, None] + idx
        rows, cols = [], []
        for a, b in (
            (self.s6, self.s6),
            (self.t6, self.t6),
            (self.s6, self.t6),
            (self.t6, self.s6),
        ):
            rows.append(np.broadcast_to(a[:, :, None], (len(source), 6, 6)).ravel())
            cols.append(np.broadcast_to(b[:, None, :], (len(source), 6, 6)).ravel())
        diagonal = np.arange(6 * n)
        rows.append(diagonal)
        cols.append(diagonal)
        r, c = np.concatenate(rows), np.concatenate(cols)
        size = 6 * n
        keys, self.slot = np.unique(c * size + r, return_inverse=True)  # column-major order
        self.indices = (keys % size).astype(np.int32)
        self.indptr = np.searchsorted(keys // size, np.arange(size + 1)).astype(np.int32)
        self.diagonal = np.searchsorted(keys, diagonal * size + diagonal)
        self.size = size

    def matrix(self, block: NDArray[np.float64]) -> NDArray[np.float64]:
        """The matrix's stored values for the edges' ``block`` (E, 6, 6): +ss, +tt, -st, -ts."""
        flat = block.ravel()
        values = np.concatenate([flat, flat, -flat, -flat, np.zeros(self.size)])
        sums = np.bincount(self.slot, weights=values, minlength=len(self.indices))
        return sums  # type: ignore[return-value]  # weighted: float64; NumPy's stubs say integer

    def csc(self, data: NDArray[np.float64], lam: float) -> sp.csc_matrix:
        """The matrix of stored values ``data`` with ``lam`` added to its diagonal."""
        damped = data.copy()
        damped[self.diagonal] += lam
        return sp.csc_matrix((damped, self.indices, self.indptr), shape=(self.size, self.size))


def _linear_system(
    g: PoseGraphArrays,
    pattern: _Pattern,
    X_inv: NDArray[np.float64],
    poses: NDArray[np.float64],
    zeta: NDArray[np.float64],
    confidence: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The weighted normal equations at ``poses``: H's stored values (``pattern``) and b
    (6N,); the target's Jacobian is minus the source's."""
    A = X_inv @ _rigid_inverse(poses)[g.target]
    Ts = poses[g.source]
    # Js[:, :, k]: the misalignment's change for a left perturbation of the source along k
    Js = np.stack([_linearised(A @ G @ Ts) for G in _GENERATORS], axis=-1)
    JtI = np.einsum("eji,ejk->eik", Js, g.information) * confidence[:, None, None]
    grad = np.einsum("eij,ej->ei", JtI, zeta)  # Jsᵀ l Λ ζ
    b = np.zeros(pattern.size)
    np.add.at(b, pattern.s6.ravel(), -grad.ravel())
    np.add.at(b, pattern.t6.ravel(), grad.ravel())
    return pattern.matrix(JtI @ Js), b


def _solve(A: sp.csc_matrix, b: NDArray[np.float64]) -> NDArray[np.float64]:
    """x with A x = b, A (n, n) symmetric positive definite and sparse: LU with a minimum
    degree ordering of A + Aᵀ and no pivoting off the diagonal (SuperLU's symmetric mode)."""
    lu = splu(
        A,
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    return lu.solve(b)


def _updated(poses: NDArray[np.float64], delta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each pose left-multiplied by its step (rotation as Z-Y-X Euler angles)."""
    d = delta.reshape(-1, 6)
    step = np.tile(np.eye(4), (len(d), 1, 1))
    step[:, :3, :3] = _euler_zyx(d[:, 0], d[:, 1], d[:, 2])
    step[:, :3, 3] = d[:, 3:]
    return step @ poses


def _euler_zyx(
    a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Rz(c) Ry(b) Rx(a), (K, 3, 3)."""
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    return np.stack(
        [
            np.stack([cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa], -1),
            np.stack([sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa], -1),
            np.stack([-sb, cb * sa, cb * ca], -1),
        ],
        axis=-2,
    )


def _pose_vector(poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """Every pose as Euler angles and translation, (6N,): only its norm is used."""
    R = poses[:, :3, :3]
    sy = np.hypot(R[:, 0, 0], R[:, 1, 0])
    regular = sy >= 1e-6
    a = np.where(regular, np.arctan2(R[:, 2, 1], R[:, 2, 2]), np.arctan2(-R[:, 1, 2], R[:, 1, 1]))
    b = np.arctan2(-R[:, 2, 0], sy)
    c = np.where(regular, np.arctan2(R[:, 1, 0], R[:, 0, 0]), 0.0)
    return np.concatenate([np.stack([a, b, c], axis=1), poses[:, :3, 3]], axis=1).ravel()


def _levenberg_marquardt(g: PoseGraphArrays, options: GraphOptions) -> PoseGraphArrays:
    """One robust optimisation of the whole graph (poses and line processes updated)."""
    mu = _line_process_weight(g, options)
    poses = g.poses.copy()
    X_inv = _rigid_inverse(g.transformation)
    zeta = _misalignment(g, X_inv, poses)
    confidence = g.confidence.copy()
    residual = _residual(g, zeta, confidence, mu)
    confidence = _confidence(g, zeta, mu)
    x = _pose_vector(poses)
    pattern = _Pattern(g.source, g.target, len(poses))
    H, b = _linear_system(g, pattern, X_inv, poses, zeta, confidence)
    lam = 1e-5 * H[pattern.diagonal].max()
    ni, rho = 2.0, 0.0
    stop = b.max() < options.min_right_term
    iteration = 0
    while not stop:
        lm = 0
        while True:
            delta = _solve(pattern.csc(H, lam), b)
            stop = np.linalg.norm(delta) < options.min_relative_increment * (
                np.linalg.norm(x) + options.min_relative_increment
            )
            if not stop:
                trial = _updated(poses, delta)
                zeta_new = _misalignment(g, X_inv, trial)
                new_residual = _residual(g, zeta_new, confidence, mu)
                rho = (residual - new_residual) / (delta @ (lam * delta + b) + 1e-3)
                if rho > 0:
                    if residual - new_residual < (
                        options.min_relative_residual_increment * residual
                    ):
                        stop = True
                        break
                    alpha = 1.0 - (2 * rho - 1) ** 3
                    lam *= max(options.lower_scale_factor, min(alpha, options.upper_scale_factor))
                    ni, residual, zeta, poses = 2.0, new_residual, zeta_new, trial
                    x = _pose_vector(poses)
                    confidence = _confidence(g, zeta, mu)
                    H, b = _linear_system(g, pattern, X_inv, poses, zeta, confidence)
                    stop = b.max() < options.min_right_term
                    if stop:
                        break
                else:
                    lam *= ni
                    ni *= 2
            lm += 1
            stop = stop or lm >= options.max_iterations_lm
            if rho > 0 or stop:
                break
        stop = stop or residual < options.min_residual or iteration >= options.max_iterations
        iteration += 1
    out = PoseGraphArrays(
        poses, g.source, g.target, g.transformation, g.information, g.uncertain, confidence
    )
    return out


def _pruned(g: PoseGraphArrays, options: GraphOptions) -> PoseGraphArrays:
    return g.edges_where(~g.uncertain | (g.confidence > options.edge_prune_threshold))


def optimise_graph(g: PoseGraphArrays, options: GraphOptions = GraphOptions()) -> PoseGraphArrays:
    """The graph optimised, its uncertain edges that disagree pruned, optimised again and
    pruned again (Open3D's ``global_optimization``); the reference node keeps its pose. A
    graph in parts that no edge ties together is returned as it is.

    Returns the optimised graph: poses (N, 4, 4) and the edges kept with their line
    processes.
    """
    if len(g.source) == 0 or len(g.poses) < 2:
        return g
    n = len(g.poses)
    links = sp.coo_matrix((np.ones(len(g.source)), (g.source, g.target)), shape=(n, n))
    if connected_components(links, directed=False)[0] > 1:
        return g  # a part of the graph nothing ties to the rest: left as it is
    first = _pruned(_levenberg_marquardt(g, options), options)
    second = _pruned(_levenberg_marquardt(first, options), options)
    r = options.reference_node
    if 0 <= r < len(g.poses):
        second.poses = (g.poses[r] @ np.linalg.inv(second.poses[r])) @ second.poses
    return second


def graph_arrays(graph: reg.PoseGraph) -> PoseGraphArrays:
    """An Open3D pose graph as arrays."""
    edges = graph.edges
    return PoseGraphArrays(
        np.array([np.asarray(node.pose) for node in graph.nodes]).reshape(-1, 4, 4),
        np.array([e.source_node_id for e in edges], dtype=np.int64),
        np.array([e.target_node_id for e in edges], dtype=np.int64),
        np.array([np.asarray(e.transformation) for e in edges]).reshape(-1, 4, 4),
        np.array([np.asarray(e.information) for e in edges]).reshape(-1, 6, 6),
        np.array([e.uncertain for e in edges], dtype=bool),
        np.array([e.confidence for e in edges], dtype=np.float64),
    )


def open3d_graph(g: PoseGraphArrays) -> reg.PoseGraph:
    """Arrays as an Open3D pose graph."""
    graph = reg.PoseGraph()
    for pose in g.poses:
        graph.nodes.append(reg.PoseGraphNode(pose))
    for k in range(len(g.source)):
        edge = reg.PoseGraphEdge(
            int(g.source[k]),
            int(g.target[k]),
            g.transformation[k],
            g.information[k],
            uncertain=bool(g.uncertain[k]),
            confidence=float(g.confidence[k]),
        )
        graph.edges.append(edge)
    return graph


def open3d_optimise(graph: reg.PoseGraph, options: GraphOptions = GraphOptions()) -> reg.PoseGraph:
    """A copy of an Open3D pose graph optimised by Open3D's own ``global_optimization``
    (its dense system), with ``options``' correspondence distance, pruning, preference and
    reference node."""
    out = reg.PoseGraph(graph)
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=options.max_correspondence_m,
        edge_prune_threshold=options.edge_prune_threshold,
        preference_loop_closure=options.preference,
        reference_node=options.reference_node,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            out,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    return out


def optimise_pose_graph(
    graph: reg.PoseGraph, options: GraphOptions = GraphOptions()
) -> reg.PoseGraph:
    """An Open3D pose graph optimised (:func:`optimise_graph`); graphs of up to
    ``DENSE_UP_TO`` nodes by Open3D itself (:func:`open3d_optimise`), whose dense system is
    faster at that size (the two agree to 1e-10 m)."""
    if len(graph.nodes) > DENSE_UP_TO:
        return open3d_graph(optimise_graph(graph_arrays(graph), options))
    return open3d_optimise(graph, options)
