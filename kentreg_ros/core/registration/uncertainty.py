"""The covariance of a registered pose: what the final fit's residuals say about its error.

The refinement (:func:`~kentreg_ros.core.registration.refine.refine_joint`) minimises
``F(delta) = sum_i a_i rho(r_i)``: point-to-plane residuals ``r_i = n_i . (q_i - x_i)`` of the
source points ``x_i`` (target frame) against the target points ``q_i`` with normals ``n_i``,
the Geman-McClure kernel ``rho`` of scale ``s`` and the normals' agreement ``a_i`` as fixed
weights, for the left perturbation ``delta = (omega, v)`` with rows ``J_i = [n_i x x_i, -n_i]``.
Its estimate solves ``sum_i a_i psi(r_i) J_i = 0`` (``psi = rho'``); to first order an error
``e_i`` of the residuals moves it by ``-A^-1 sum_i a_i psi'(r_i) e_i J_i``, so (Huber 1981,
ch. 6; the cluster-robust form of Liang & Zeger 1986)::

    Cov(delta) = k * A^-1 M A^-1
    A = sum_i a_i psi'(r_i) J_i J_i^T = sum_i w_i (s^2 - 3 r_i^2) / (s^2 + r_i^2) J_i J_i^T
    M = G / (G - 6) * sum_c g_c g_c^T,   g_c = sum_{i in cluster c} w_i r_i J_i

with ``w_i = a_i psi(r_i) / r_i`` the IRLS weights of the last Gauss-Newton iteration. Its
terms, and what each stands for:

- ``A``, the robust cost's own curvature, not IRLS's ``sum w J J^T``: the kernel's slope
  ``psi`` flattens towards its scale and turns beyond ``s / sqrt(3)``, so a residual there
  holds the pose less than its IRLS weight says (the robust kernel's down-weighting). Clamped
  from below at :data:`CURVATURE_FLOOR` of IRLS's information, along directions where the
  kernel is flat or concave.
- ``M``, the noise the residuals show, not a variance assumed: the sensor's range noise
  averaged over a voxel, the voxel centroids' offsets from the surface, the target normals'
  errors times the in-plane offset ``n . (q - x)``, and what the kernel kept of the outliers.
- Summed per cubic cell of :data:`CELL_SPACINGS` sampling spacings before squaring: the
  correspondences of one surface patch share their errors (a target normal is fitted over 15
  neighbouring voxels, the voxels of one surface are cut alike by the grid), so N of them are
  not N independent measurements; the cells are. A sparse scan has few, and a direction held
  by a few patches (a corridor's door frames) gets the variance of those few. ``G / (G - 6)``
  corrects for the six parameters fitted to the same residuals (the scores ``g_c`` sum to zero
  at the solution).
- And summed per plane (rows whose target normals fall in one bin of about 20 degrees and whose
  offsets ``n . x`` lie in one slab of the cell's edge), ``M`` raised to that scatter along the
  directions where it is the larger: a plane's rows share errors over its whole extent, which
  the cells cannot see (it is common to all of them). The sensor's sampling pattern and the
  voxel grid cut a plane alike along its length (a wall parallel to the sensor's axes is cut
  at one phase over all its voxels), so the centroids of a wall sit off it by an amount of
  its own, which changes as the sensor moves across it. Where a few planes hold a direction
  (a corridor's two walls, the lateral axis) that shared offset is most of the error: in the
  simulated corridor the lateral error was 0.6 mm against a sigma of 0.33 mm from the cells,
  deterministic for a given pair (the scatter over re-drawn noise, 0.2-0.3 mm, matched the
  cells' sigma) and about 4 % of the lateral motion; the walls' raw sums show it, with the
  cells' ``G / (G - 6)`` (not the planes' own: with a few planes that factor would multiply
  the noise of a few numbers).
- ``k`` = :data:`CALIBRATION`, fitted on simulated sequences with exact poses: what the
  first-order sandwich leaves out (correspondences chosen again by nearest neighbour as the
  pose moves, weights that depend on the pose, the convergence tolerance).

Along the translation directions the degeneracy test leaves unresolved (a pose moved by the
distinct distance either way fits about as well,
:func:`~kentreg_ros.core.registration.robust.register_robust`), no residual can say where the
pose is: :func:`inflate_degenerate` adds the square of that distance. In a corridor a spinning
sensor's rings pull the step towards no motion along the axis, so the error there is about
the motion along it. The other parameters' response to a pose pinned along the axis (the
coupling ``-A_oo^-1 A_ou`` of the curvature) is left out: in the simulated corridor it
predicted none of the lateral error (correlation -0.07, 0.07 mm against 0.6 mm). No
systematic floor per cell (a share of the voxel edge) is added: the grid's effects show in the
residuals, where ``M`` counts them (per plane where they are common to a plane), and on the
simulated scans such a floor overstated the errors.

The rows use the point-to-plane residual for either refinement method (plane-to-plane's
estimate has about the same uncertainty). The measurements behind these choices are in
docs/covariance.md, the calibration in ``benchmarks/results/calibration.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Edge of the cells whose residuals are taken as one measurement, in sampling spacings: a
#: target normal's 15 neighbours span about 4 spacings across, so a cell of 8 holds patches
#: whose normals and voxels share most of their errors.
CELL_SPACINGS = 8.0
#: Variance factor ``k``, fitted on simulated sequences with exact poses (noise levels, raw
#: outliers, sparse scans; previous scan and local map, a local-map step with the model pose's
#: own error added, :attr:`~kentreg_ros.core.odometry.models.ModelStrategy.anchor`). The pooled
#: fit (median NEES at the 6-DOF chi-square's 5.35) gives about 0.85, but the two models sit
#: on either side of it (the previous scan's steps want about 1.15, the local map's about 0.8),
#: so ``k`` is taken where neither leaves issue #40's bars: at 1.0 the previous scan's 5 cm
#: noise covers x on about 86 % of its steps at 2 sigma (bar 85 %), at 1.25 the local map's
#: clean scene has a median NEES of about 3.0 (bar 3). Not tuned on the real sequences.
CALIBRATION = 1.1
#: Least curvature of the robust cost along any direction, as a share of the IRLS information
#: along it: where residuals beyond the kernel's inflection dominate, ``A`` can be flat or
#: indefinite, and the pose is then held about this weakly.
CURVATURE_FLOOR = 0.05
#: Variance (m^2, rad^2) of a direction without any information, as
#: :func:`~kentreg_ros.core.registration.result.information_to_covariance` gives it.
NULL_VARIANCE = 1e6
#: The rows of ``J``: ``(omega, v)`` -> ``(x, y, z, roll, pitch, yaw)``.
_TO_XYZ = [3, 4, 5, 0, 1, 2]


@dataclass(frozen=True, eq=False)
class Residuals:
    """The rows of the refinement's last Gauss-Newton iteration.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
        Matched source points in the target frame.
    normals : ndarray, shape (n, 3)
        Normals of their target points.
    residuals : ndarray, shape (n,)
        Point-to-plane residuals ``n . (q - x)`` (m).
    weights : ndarray, shape (n,)
        IRLS weights: the Geman-McClure weight times the normals' agreement.
    scale : float
        The Geman-McClure scale ``s`` of those weights (m).
    """

    points: FloatArray
    normals: FloatArray
    residuals: FloatArray
    weights: FloatArray
    scale: float

    def __len__(self) -> int:
        return len(self.residuals)


def pose_covariance(
    rows: Residuals,
    spacing: float,
    *,
    cell_spacings: float = CELL_SPACINGS,
    calibration: float = CALIBRATION,
) -> FloatArray:
    """Covariance of a refined pose from its last iteration's rows (see the module docstring).

    Parameters
    ----------
    rows : Residuals
        The refinement's last rows.
    spacing : float
        The clouds' sampling spacing (the voxel edge, m); 0 makes every row its own cell.
    cell_spacings : float
        Edge of the cells of shared errors, in spacings.
    calibration : float
        The variance factor ``k``.

    Returns
    -------
    ndarray, shape (6, 6)
        In the order (x, y, z, roll, pitch, yaw) for the left perturbation
        ``T_true = exp(delta) T`` in the target frame, the convention of
        :attr:`~kentreg_ros.core.registration.result.RegistrationResult.covariance`.
    """
    r, w = rows.residuals, rows.weights
    J = _jacobian(rows.points, rows.normals)  # (6, n): one row of J per column
    s2, r2 = rows.scale**2, r * r
    H = (J * w) @ J.T  # IRLS's information
    A = (J * (w * (s2 - 3.0 * r2) / (s2 + r2))) @ J.T  # the robust cost's curvature
    scores = J * (w * r)
    if spacing > 0.0:
        edge = cell_spacings * spacing
        cells = _key_sums(_cell_keys(rows.points, edge), scores)
        planes = _key_sums(_plane_keys(rows.points, rows.normals, edge), scores)
        factor = _dof_factor(cells.shape[1])
        M = _larger(factor * (cells @ cells.T), factor * (planes @ planes.T))
    else:
        M = _dof_factor(scores.shape[1]) * (scores @ scores.T)
    V, lam, null = _eigen_split(H)
    A_inv = _clamped_inverse(A, V, lam)
    cov = calibration * (A_inv @ M @ A_inv) + NULL_VARIANCE * (null @ null.T)
    out: FloatArray = np.asarray(cov[np.ix_(_TO_XYZ, _TO_XYZ)], dtype=np.float64)
    return 0.5 * (out + out.T)


def inflate_degenerate(
    covariance: FloatArray,
    directions: FloatArray,
    sigma: float,
    *,
    rotation_axis: FloatArray | None = None,
    sigma_rotation: float = 0.0,
) -> FloatArray:
    """``covariance`` with ``sigma^2 d d^T`` added along each unresolved translation direction
    ``d`` and ``sigma_rotation^2 u u^T`` about an unresolved rotation axis ``u``.

    Parameters
    ----------
    covariance : ndarray, shape (6, 6)
        Order (x, y, z, roll, pitch, yaw).
    directions : ndarray, shape (D, 3)
        Unit translation directions (target frame).
    sigma : float
        Standard deviation added along each (m).
    rotation_axis : ndarray, shape (3,), optional
        Unit rotation axis the data do not hold.
    sigma_rotation : float
        Standard deviation added about it (rad).
    """
    out = np.array(covariance, dtype=np.float64)
    for d in np.asarray(directions, dtype=np.float64).reshape(-1, 3):
        out[:3, :3] += sigma**2 * np.outer(d, d)
    if rotation_axis is not None:
        u = np.asarray(rotation_axis, dtype=np.float64)
        out[3:, 3:] += sigma_rotation**2 * np.outer(u, u)
    return out


def _jacobian(points: FloatArray, normals: FloatArray) -> FloatArray:
    """The rows ``[n x p, -n]`` as columns, shape (6, n) (contiguous rows: the Gram products
    are then one small matrix product)."""
    p, n = points.T, normals.T
    J = np.empty((6, len(points)))
    np.multiply(n[1], p[2], out=J[0])
    J[0] -= n[2] * p[1]
    np.multiply(n[2], p[0], out=J[1])
    J[1] -= n[0] * p[2]
    np.multiply(n[0], p[1], out=J[2])
    J[2] -= n[1] * p[0]
    np.negative(n, out=J[3:])
    return J


def _eigen_split(H: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Eigenvectors of ``H`` with information (eigenvalue above 1e-9 of the largest), their
    eigenvalues, and the eigenvectors without."""
    evals, evecs = np.linalg.eigh(0.5 * (H + H.T))
    keep = evals > 1e-9 * max(float(evals[-1]), 1e-300)
    return evecs[:, keep], evals[keep], evecs[:, ~keep]


def _clamped_inverse(A: FloatArray, V: FloatArray, lam: FloatArray) -> FloatArray:
    """Inverse of ``A`` on the range of ``H = V diag(lam) V^T``, its eigenvalues relative to
    ``H``'s clamped at :data:`CURVATURE_FLOOR` (``A`` is then at least that share of ``H`` in
    every direction)."""
    Hh = V / np.sqrt(lam)  # H^(-1/2) on its range
    b, U = np.linalg.eigh(Hh.T @ A @ Hh)
    W = Hh @ U
    out: FloatArray = (W / np.maximum(b, CURVATURE_FLOOR)) @ W.T
    return out


#: Largest number of cells per row for which the cells' sums are a dense count over the grid
#: (one pass each); beyond it the occupied cells are found by sorting.
_DENSE_CELLS_PER_ROW = 4
#: Bins per unit of each component of a plane's normal (:func:`_plane_keys`): 7 values from -1
#: to 1, bins about 20 degrees wide, well above the scatter of one plane's fitted normals.
_NORMAL_BINS = 3.0


def _dof_factor(G: int) -> float:
    """``G / (G - 6)``: the scores of ``G`` clusters sum to zero along the six fitted
    parameters."""
    return G / max(G - 6, 1)


def _larger(M_cells: FloatArray, M_planes: FloatArray) -> FloatArray:
    """``M_cells`` raised to ``M_planes`` along the directions where the planes' scatter is the
    larger (their generalised eigenvectors; unchanged where the cells' is larger or has none):
    the smallest matrix at least as large as either along every direction that the cells'
    eigenvectors span."""
    lam, V = np.linalg.eigh(M_cells)
    keep = lam > 1e-12 * max(float(lam[-1]), 1e-300)
    root = V[:, keep] * np.sqrt(lam[keep])  # M_cells = root @ root.T on its range
    whiten = V[:, keep] / np.sqrt(lam[keep])
    b, U = np.linalg.eigh(whiten.T @ M_planes @ whiten)
    W = root @ U
    out: FloatArray = M_cells + (W * np.maximum(b - 1.0, 0.0)) @ W.T
    return out


def _cell_keys(points: FloatArray, edge: float) -> NDArray[np.intp]:
    """The cubic cell of edge ``edge`` of each of ``points`` (n, 3), as a linear index over the
    grid's bounding box."""
    g = np.floor(points * (1.0 / edge))
    lo = [float(g[:, axis].min()) for axis in range(3)]  # column by column: much faster
    span = [float(g[:, axis].max()) - lo[axis] + 1.0 for axis in range(3)]
    linear = ((g[:, 0] - lo[0]) * span[1] + (g[:, 1] - lo[1])) * span[2] + (g[:, 2] - lo[2])
    keys: NDArray[np.intp] = linear.astype(np.intp)
    return keys


def _plane_keys(points: FloatArray, normals: FloatArray, edge: float) -> NDArray[np.intp]:
    """The plane of each row: its normal's bin (:data:`_NORMAL_BINS`) and its offset
    ``n . x`` in slabs of ``edge``, as one index."""
    b = np.rint(normals * _NORMAL_BINS) + _NORMAL_BINS  # 0 .. 2 * bins in each component
    side = 2.0 * _NORMAL_BINS + 1.0
    direction = (b[:, 0] * side + b[:, 1]) * side + b[:, 2]
    offset = np.floor(np.einsum('ij,ij->i', normals, points) * (1.0 / edge))
    keys: NDArray[np.intp] = (direction + side**3 * (offset - offset.min())).astype(np.intp)
    return keys


def _key_sums(keys: NDArray[np.intp], values: FloatArray) -> FloatArray:
    """Sums of the columns of ``values`` (k, n) over the distinct ``keys`` (n,) (non-negative
    integers): shape (k, G), G the distinct keys."""
    size = float(keys.max()) + 1.0
    if size > _DENSE_CELLS_PER_ROW * len(keys):  # sparse keys: number the occupied ones
        keys = np.unique(keys, return_inverse=True)[1].reshape(-1)
        size = float(keys.max()) + 1.0
    n_cells = int(size)
    k = len(values)
    # One pass for every column: row i of column j counts in bin (key_i * k + j).
    bins = (keys[None, :] * k + np.arange(k)[:, None]).ravel()
    sums = np.bincount(bins, weights=values.ravel(), minlength=n_cells * k).reshape(-1, k).T
    occupied = np.bincount(keys, minlength=n_cells) > 0
    out: FloatArray = np.asarray(sums[:, occupied], dtype=np.float64)
    return out
