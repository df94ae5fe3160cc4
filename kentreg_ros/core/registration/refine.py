"""Joint 6-DOF refinement on positions and Kent-weighted normals.

The hybrid direction of G-IMLOP (Billings & Taylor 2015) and Min et al. (2019) cited by the
paper: every correspondence carries a positional term and an orientational term. Here the
positional term is point-to-plane, or plane-to-plane with GICP-style covariances (Segal et al.
2009) built from our normals, and the orientational term enters as a Kent/von Mises-Fisher
likelihood weight ``exp(kappa (n_q . R n_p - 1))`` of the two normals. A Geman-McClure kernel on
the point-to-plane distance rejects outliers. Solved by Gauss-Newton on SE(3) with the left
perturbation ``T <- exp(delta) T``, ``delta = (omega, v)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import kernels
from kentreg_ros.core.geometry import exp_so3, hat, make_transform, project_to_so3
from kentreg_ros.core.registration.correspondence import NearestNeighborCache
from kentreg_ros.core.registration.translation import geman_mcclure_weights, robust_scale
from kentreg_ros.core.registration.uncertainty import Residuals
from kentreg_ros.core.scan.neighbors import NeighborIndex

FloatArray = NDArray[np.float64]

#: GICP's planar covariance ``I - (1 - eps) n n^T`` (Segal et al. 2009 use 1e-3): the normal
#: direction is a thousand times more certain than the in-plane ones.
PLANE_EPSILON = 1e-3
#: Concentration of the normal-agreement weight, re-estimated from the residual normals each
#: iteration and clipped: at 5 a 40 deg disagreement still keeps ~30 % weight (wide basin); 500
#: (2.6 deg) is the spread of PCA normals of one plane, finer would weigh noise.
NORMAL_KAPPA_RANGE = (5.0, 500.0)
#: Fewest correspondences for a 6-DOF Gauss-Newton step (twice the unknowns).
MIN_CORRESPONDENCES = 12
#: The correspondence gate shrinks by this factor per iteration from the start gate to the
#: floor: a few iterations of a wide basin, then precision (0.7^6 ~ 1/8).
GATE_SHRINK = 0.7
#: Consecutive steps whose (metric-weighted) directions agree to this cosine are a creep and get
#: lengthened (see :func:`_step_scale`).
CREEP_COSINE = 0.9


@dataclass(frozen=True)
class RefineResult:
    """Outcome of :func:`refine_joint`.

    Attributes
    ----------
    T : ndarray, shape (4, 4)
        Refined ``T_target_source``.
    hessian : ndarray, shape (6, 6)
        Gauss-Newton information matrix in (omega, v) order.
    sigma2 : float
        Weighted mean squared (Mahalanobis) residual.
    iterations : int
    converged : bool
    inlier_fraction : float
        Fraction of source points with a gated correspondence at the end.
    kappa_normal : float
        Concentration used for the normal weights at the end.
    residuals : Residuals or None
        The point-to-plane rows of the iteration ``hessian`` comes from, for
        :func:`~kentreg_ros.core.registration.uncertainty.pose_covariance` (None: no
        iteration had enough correspondences).
    """

    T: FloatArray
    hessian: FloatArray
    sigma2: float
    iterations: int
    converged: bool
    inlier_fraction: float
    kappa_normal: float
    residuals: Residuals | None = None


def inverse_3x3_symmetric(M: FloatArray) -> FloatArray:
    """Inverse of a stack of symmetric 3x3 matrices by the adjugate, shape (N, 3, 3)."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    det = a * A + b * B + c * C
    inv = np.empty_like(M)
    inv[:, 0, 0] = A
    inv[:, 0, 1] = inv[:, 1, 0] = B
    inv[:, 0, 2] = inv[:, 2, 0] = C
    inv[:, 1, 1] = a * f - c * c
    inv[:, 1, 2] = inv[:, 2, 1] = b * c - a * e
    inv[:, 2, 2] = a * d - b * b
    out: FloatArray = np.asarray(inv / det[:, None, None], dtype=np.float64)
    return out


def _solve_spd(H: FloatArray, g: FloatArray) -> FloatArray:
    reg = 1e-9 * max(float(np.trace(H)), 1e-12)
    out: FloatArray = np.asarray(np.linalg.solve(H + reg * np.eye(len(H)), g), dtype=np.float64)
    return out


def refine_joint(
    T0: FloatArray,
    source: FloatArray,
    source_normals: FloatArray,
    target: FloatArray,
    target_normals: FloatArray,
    target_tree: NeighborIndex,
    *,
    method: str = 'point_to_plane',
    normal_weight: bool = True,
    max_iterations: int = 50,
    max_distance: float = 1.0,
    min_distance: float = 0.1,
    tolerance: float = 5e-5,
    noise_floor: float = 0.005,
    kappa_range: tuple[float, float] = NORMAL_KAPPA_RANGE,
    neighbors: NearestNeighborCache | None = None,
    max_step_scale: float = 16.0,
) -> RefineResult:
    """Refine ``T_target_source`` by robust, normal-weighted Gauss-Newton.

    Parameters
    ----------
    T0 : ndarray, shape (4, 4)
        Start (the decoupled rotation/translation estimate).
    source, source_normals : ndarray, shape (N, 3)
    target, target_normals : ndarray, shape (M, 3)
    target_tree : NeighborIndex
        Tree on ``target``.
    method : {'plane_to_plane', 'point_to_plane'}
    normal_weight : bool
        Multiply each correspondence's weight by ``exp(kappa (n_q . R n_p - 1))``, kappa being
        re-estimated from the current normal residuals (clipped to ``kappa_range``).
    max_distance, min_distance : float
        The correspondence gate shrinks geometrically from the first to the second.
    neighbors : NearestNeighborCache, optional
        Correspondence cache over ``target_tree`` and ``source`` (e.g. the translation
        stage's); the nearest neighbours are exact either way.
    max_step_scale : float
        Largest factor by which consecutive steps in the same direction are lengthened once
        the gate is at ``min_distance`` (1 disables it; the step control is
        :func:`_step_scale`'s).
    """
    R = T0[:3, :3].copy()
    t = T0[:3, 3].copy()
    nn = neighbors or NearestNeighborCache(target_tree, target, len(source))
    gate = max_distance
    H = np.zeros((6, 6))
    sigma2 = 0.0
    inlier = 0.0
    kappa_n = kappa_range[0]
    converged = False
    steps = _StepControl(_displacement_metric(source), max_step_scale)
    last: _Rows | None = None
    it = 0
    for it in range(1, max_iterations + 1):
        x = source @ R.T + t
        _, idx = nn.query(x, gate)
        ok, r_plane, cos = kernels.plane_residuals(
            x, idx, target, target_normals, source_normals, R
        )
        if len(ok) < MIN_CORRESPONDENCES:
            break
        w = geman_mcclure_weights(r_plane, robust_scale(r_plane, noise_floor))
        if normal_weight:
            w, kappa_n = _normal_weighted(w, cos, kappa_range)
        H, g, sigma2 = _normal_equations(
            method, x, idx, ok, target, target_normals, source_normals, R, r_plane, w
        )
        last = (x, idx, ok, r_plane, w)
        delta = steps.scaled(-_solve_spd(H, g), at_floor=gate <= min_distance)
        dR = exp_so3(delta[:3])
        R = project_to_so3(dR @ R)
        t = dR @ t + delta[3:]
        inlier = len(ok) / len(source)
        gate = max(gate * GATE_SHRINK, min_distance)
        small = max(np.linalg.norm(delta[:3]), np.linalg.norm(delta[3:])) < tolerance
        if small and gate <= min_distance:
            converged = True
            break
    return RefineResult(
        T=make_transform(R, t),
        hessian=H,
        sigma2=sigma2,
        iterations=it,
        converged=converged,
        inlier_fraction=inlier,
        kappa_normal=kappa_n,
        residuals=None if last is None else _residuals(last, target_normals, noise_floor),
    )


#: One iteration's rows: the moved source points, their neighbours, the matched rows, the
#: point-to-plane residuals and the weights.
_Rows = tuple[FloatArray, NDArray[np.intp], NDArray[np.intp], FloatArray, FloatArray]


def _residuals(rows: _Rows, target_normals: FloatArray, noise_floor: float) -> Residuals:
    """The matched rows of one iteration as :class:`Residuals`, with the kernel's scale
    (computed again from the residuals: the same value)."""
    x, idx, ok, r, w = rows
    x_ok, n_ok = np.take(x, ok, axis=0), np.take(target_normals, idx[ok], axis=0)
    return Residuals(x_ok, n_ok, r, w, robust_scale(r, noise_floor))


def _normal_weighted(
    w: FloatArray, cos: FloatArray, kappa_range: tuple[float, float]
) -> tuple[FloatArray, float]:
    """The weights times the Kent (von Mises-Fisher) likelihood of the normals' agreement,
    ``exp(kappa_n (cos - 1))``, with ``kappa_n`` the inverse of the weighted mean of
    ``1 - cos`` (clipped to ``kappa_range``)."""
    resid = np.maximum(1.0 - cos, 0.0)
    kappa_n = float(
        np.clip(1.0 / max(float(np.average(resid, weights=w + 1e-12)), 1e-9), *kappa_range)
    )
    return w * np.exp(kappa_n * (cos - 1.0)), kappa_n


def _displacement_metric(source: FloatArray) -> FloatArray:
    """Weights that turn a step ``(omega, v)`` into displacements: the source's RMS radius for
    the rotation, 1 for the translation."""
    centred = source - source.mean(axis=0)
    radius = float(np.sqrt(np.einsum('ij,ij->', centred, centred) / max(len(source), 1)))
    return np.array([radius] * 3 + [1.0] * 3)


class _StepControl:
    """The refinement's step length: each Gauss-Newton step scaled by :func:`_step_scale`'s
    rule against the step before it (halved on a reversal, lengthened while creeping)."""

    def __init__(self, metric: FloatArray, max_scale: float) -> None:
        self.metric, self.max_scale = metric, max_scale
        self.scale = 1.0
        self.previous: FloatArray | None = None

    def scaled(self, delta: FloatArray, *, at_floor: bool) -> FloatArray:
        """``delta`` times the scale it earns against the previous (unscaled) step."""
        if self.previous is not None:
            self.scale = _step_scale(
                delta, self.previous, self.scale, self.metric, at_floor, self.max_scale
            )
        self.previous = delta
        out: FloatArray = self.scale * delta
        return out


def _step_scale(
    delta: FloatArray,
    prev_delta: FloatArray,
    scale: float,
    metric: FloatArray,
    at_floor: bool,
    max_scale: float,
) -> float:
    """The step's scale: halved when the step reverses the last one; doubled (up to
    ``max_scale``) while the gate is at its floor and the step continues the last one's
    direction (cosine above :data:`CREEP_COSINE` in the displacement metric).

    Nearest-neighbour correspondences make Gauss-Newton alternate between two correspondence
    sets, or creep: converge linearly, by many small steps in one direction, along weakly
    constrained directions (on the real small_gicp pair ~0.15 mrad per iteration for 100+
    iterations). Halving on a reversal collapses a cycle onto its midpoint; doubling while the
    direction holds (rotations weighted by the RMS radius of the source, ``metric``, so both
    parts count as displacements) shortens a creep. A fixed tolerance on the step then stops
    close to the fixed point instead of at an arbitrary point of a creep.
    """
    if float(delta @ prev_delta) < 0.0:
        return scale * 0.5
    if at_floor and scale < max_scale:
        a, b = delta * metric, prev_delta * metric
        if float(a @ b) > CREEP_COSINE * float(np.linalg.norm(a) * np.linalg.norm(b)):
            return min(2.0 * scale, max_scale)
    return scale


def _normal_equations(
    method: str,
    x: FloatArray,
    idx: NDArray[np.intp],
    ok: NDArray[np.intp],
    target: FloatArray,
    target_normals: FloatArray,
    source_normals: FloatArray,
    R: FloatArray,
    r_plane: FloatArray,
    w: FloatArray,
) -> tuple[FloatArray, FloatArray, float]:
    """Gauss-Newton's ``H``, ``g`` and the weighted mean squared residual of one iteration.

    ``J = d e / d delta = [hat(x), -I]`` for the left perturbation ``delta = (omega, v)``.
    """
    if method == 'plane_to_plane':
        return _plane_to_plane_equations(x, idx, ok, target, target_normals, source_normals, R, w)
    H, g, wrr, wsum = kernels.plane_normal_equations(x, idx, ok, target_normals, r_plane, w)
    return H, g, wrr / max(wsum, 1e-12)


def _plane_to_plane_equations(
    x: FloatArray,
    idx: NDArray[np.intp],
    ok: NDArray[np.intp],
    target: FloatArray,
    target_normals: FloatArray,
    source_normals: FloatArray,
    R: FloatArray,
    w: FloatArray,
) -> tuple[FloatArray, FloatArray, float]:
    """GICP-like normal equations ``H`` (6, 6), ``g`` (6,) and the weighted residual variance
    over the rows ``ok``: the residual vector weighted by the inverse of the combined covariance
    ``C_q + R C_p R^T`` with planar ``C = I - (1 - eps) n n^T``."""
    j = idx[ok]
    xo = np.take(x, ok, axis=0)  # np.take: several times faster than fancy indexing
    e = np.take(target, j, axis=0) - xo  # residual vector, (n, 3)
    nq = np.take(target_normals, j, axis=0)
    np_rot = np.take(source_normals, ok, axis=0) @ R.T
    cov = 2.0 * np.eye(3)[None] - (1.0 - PLANE_EPSILON) * (
        nq[:, :, None] * nq[:, None, :] + np_rot[:, :, None] * np_rot[:, None, :]
    )
    W = inverse_3x3_symmetric(cov) * w[:, None, None]
    We = np.einsum('nab,nb->na', W, e)
    # J^T W J and J^T W e in closed form: hat(x)^T W hat(x) = -hat(x) W hat(x).
    hx = hat(xo)
    WJw = np.matmul(W, hx)  # W hat(x), (n, 3, 3)
    H = np.empty((6, 6))
    H[:3, :3] = -np.tensordot(hx, WJw, axes=([0, 2], [0, 1]))
    # J_w^T W J_v = hat(x)^T W (-I) = hat(x) W; tensordot gives hat(x)^T W.
    H[:3, 3:] = -np.tensordot(hx, W, axes=([0, 1], [0, 1]))
    H[3:, :3] = H[:3, 3:].T
    H[3:, 3:] = W.sum(axis=0)
    g = np.concatenate([-np.einsum('nab,nb->a', hx, We), -We.sum(axis=0)])
    sigma2 = float(np.einsum('na,na->', e, We) / max(float(w.sum()), 1e-12))
    return H, g, sigma2
