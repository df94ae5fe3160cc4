"""EM on the unit sphere: rotation from surface normals with Kent (FB5) mixtures.

Both variants maximise the paper's likelihood (its eqs. fb5-ll): every model normal ``y_m``
is the mean of one Kent component, the components of a normal cluster share ``kappa``,
``beta``, ``gamma1`` and ``gamma2``, and a uniform component of weight ``pi0`` takes the
outliers::

    p(x_n) = sum_m pi_m FB5(R x_n | y_m; kappa, beta, gamma1, gamma2) + pi0 p0.

* :func:`paper_cluster_em` is Algorithm 2 of Fahandezh-Saadi et al. for one pair of clusters
  (``p0 = 1/N``); the paper runs it on every pair of separately clustered clusters and averages
  the rotations (its eq. rot_avg).
* :func:`shared_rotation_em` maximises the same likelihood over all clusters at once: the
  partition is the model's (its clusters' Kent frames), each observed normal joins the model
  cluster nearest to it under the current rotation, and one M-step solves for the single
  rotation shared by all clusters, ``argmin_R sum_k beta_k tr(R^T A_k R B_k) - tr(R C)`` with
  ``C = sum_k kappa_k sum_mn tau_mn x_n y_m^T`` (the paper's eq. solve_for_R summed over the
  clusters). The per-cluster Kent parameters come from the paper's weighted moment estimate
  of the rotated observed normals (:func:`~kentreg_ros.core.kent.fit_kent_moments_batch`).

Why the shared M-step: each cluster alone fixes only two of the three rotation angles (its
twist about its own mean normal is weakly determined), and averaging per-cluster rotations
passes those drifts on; a rotation fitted to all clusters at once is determined by all of
them. Normals are summarised as weighted bins (:class:`NormalBins`), so the ``M x N``
posterior matrix of the paper stays small without discarding normals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.special import logsumexp

from kentreg_ros.core import kernels
from kentreg_ros.core.geometry import rotation_angle
from kentreg_ros.core.kent import MAX_BETA_RATIO, fit_kent_moments, kent_log_normalizer
from kentreg_ros.core.registration.rotations import (
    KentRotationProblem,
    average_rotations,
    procrustes,
    solve_kent_rotation,
)
from kentreg_ros.core.scan.clusters import ModelClusters, NormalBins, kent_moments_of_sums

FloatArray = NDArray[np.float64]


LOG_UNIFORM_SPHERE = -np.log(4.0 * np.pi)


@dataclass(frozen=True)
class EMResult:
    """Outcome of an EM run on normals.

    Attributes
    ----------
    R : ndarray, shape (3, 3)
        Rotation taking observed normals onto model normals (``y ~ R x``).
    kappa, beta : ndarray, shape (K,)
        Kent concentration and ovalness per cluster, Kent's (1982) moment estimates at the
        final rotation (``beta`` is estimated even where the kernels do not use it).
    log_likelihood : list of float
        Observed-data log-likelihood after each E-step.
    iterations : int
    converged : bool
    inlier_fraction : float
        Share of the observed normals' posterior mass not given to the outlier component.
    hessian : ndarray, shape (3, 3)
        Riemannian Hessian of the negative expected log-likelihood at ``R`` (rotation
        information; a near-zero eigenvalue means rotation about that axis is undetermined).
    """

    R: FloatArray
    kappa: FloatArray
    beta: FloatArray
    log_likelihood: list[float]
    iterations: int
    converged: bool
    inlier_fraction: float
    hessian: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))


#: A singular value of the M-step's ``C`` below this share of the largest counts as zero: the
#: rotation about that direction is then not determined by ``tr(R C)`` alone.
_WAHBA_RANK_TOLERANCE = 1e-6


def _shared_m_step(problem: KentRotationProblem, R: FloatArray) -> FloatArray:
    """The M-step's rotation from the current ``R``.

    Without the ovalness term (all ``A_k = 0``, the default von Mises-Fisher kernels) the
    objective is ``-tr(R C)``: Wahba's problem, whose minimiser is the SVD solution when ``C``
    has rank 2 or more (:func:`procrustes`), with no Newton iterations. Otherwise (Kent
    kernels, or ``C`` of rank 1, where the twist about the one direction is free and the
    solver keeps the current one), Newton steps from the better of ``R`` and that solution.
    """
    start = procrustes(problem.C)
    if not problem.A.any():
        sv = np.linalg.svd(problem.C, compute_uv=False)
        if sv[1] > _WAHBA_RANK_TOLERANCE * sv[0]:
            return start
    R_new, _ = solve_kent_rotation(problem, min([R, start], key=problem.value))
    return R_new


def _rotation_tolerance_reached(R_old: FloatArray, R_new: FloatArray, tol: float) -> bool:
    return rotation_angle(R_old.T @ R_new) < max(tol, 1e-12)


@dataclass(frozen=True)
class _ModelTerms:
    """What the E-step needs of the model, fixed across passes: the bins' directions ``y``,
    their mean resultants ``ym`` (a bin stands for its normals: ``y_m`` its mean resultant,
    the kernel means' average), the clusters' bin offsets and the log mixture weights."""

    y: FloatArray
    ym: FloatArray
    off: NDArray[np.intp]
    log_pi: FloatArray

    @classmethod
    def of(cls, model: ModelClusters, outlier_weight: float) -> _ModelTerms:
        y = model.bins.directions
        vy = model.bins.weights
        off = model.offsets
        log_pi = np.empty(len(y))
        for j in range(len(model)):
            sl = slice(off[j], off[j + 1])
            log_pi[sl] = np.log((1.0 - outlier_weight) * vy[sl] / max(vy[sl].sum(), 1e-300))
        return cls(y, model.bins.resultants / model.bins.weights[:, None], off, log_pi)


def _shared_e_step(
    z: FloatArray,
    observed: NormalBins,
    fixed: _ModelTerms,
    assign: NDArray[np.intp],
    log_c: FloatArray,
    kappa: FloatArray,
    beta: FloatArray,
    gamma: FloatArray,
    log_out: float,
) -> tuple[FloatArray, float, FloatArray, FloatArray]:
    """E-step of :func:`shared_rotation_em` over the clusters (``z``: the rotated observed
    directions, ``assign``: their clusters): the clusters' ``C_k``, the log-likelihood, and
    the posterior mass of every observed bin, weighted and per normal.

    For the observed bin ``n`` (weight ``w_n``) assigned to cluster ``k``::

        tau_mn = w_n pi_m FB5(R x_n | y_m) / p(x_n),   pi_m = (1 - pi0) v_m / sum_m' v_m'

    over the model bins ``m`` of cluster ``k`` (weights ``v_m``), and
    ``C_k = kappa_k sum_mn tau_mn x_n y_m^T``.

    Cost: a real scan's E-step has tens of thousands of terms (a few clusters of a few hundred
    bins on either side). Where numpy's ``exp`` is libm's (x86-64 without AVX-512), the
    exponentials are most of it; where it is numpy's own (AVX-512), they are a small part and
    the rest is numpy's dozen calls per cluster, so :func:`~kentreg_ros.core.kernels.e_step`
    writes and sums the terms in compiled passes and leaves only ``exp`` and ``log`` to numpy.
    No term can be skipped, as very few of them lie below ``exp(-40)`` on real scans (figures
    in ``docs/notes-registration.md``).
    """
    return kernels.e_step(
        z,
        assign,
        observed.weights,
        observed.resultants,
        fixed.y,
        fixed.ym,
        fixed.off,
        fixed.log_pi,
        log_c,
        kappa,
        beta,
        gamma,
        log_out,
    )


def _m_step(
    observed: NormalBins,
    Cs: FloatArray,
    tn: FloatArray,
    t_unit: FloatArray,
    assign: NDArray[np.intp],
    beta: FloatArray,
    gamma: FloatArray,
    R: FloatArray,
    rotation: str,
    kappa_m: FloatArray,
    beta_m: FloatArray,
) -> tuple[FloatArray, KentRotationProblem, FloatArray]:
    """M-step of :func:`shared_rotation_em`: the rotation (shared, or per cluster and averaged),
    then the clusters' Kent parameters from the rotated normals' moments (updated in place in
    ``kappa_m``, ``beta_m`` and ``gamma``). Returns the rotation, its problem and the
    clusters' posterior masses::

        R = argmin_R sum_k beta_k tr(R^T A_k R B_k) - tr(R C),
        A_k = g2 g2^T - g1 g1^T,  B_k = sum_n T_n x_n x_n^T,  C = sum_k C_k,
        T_n = sum_m tau_mn,

    then ``(kappa_k, beta_k, gamma_k)`` by Kent's (1982) moment estimate from the first and
    second moments of the rotated normals ``R x_n`` assigned to cluster ``k``, weighted by
    ``w_n`` (the formula is in :func:`~kentreg_ros.core.kent.fit_kent_moments_batch`). The
    paper weights these moments by ``T_n``; that lets the estimate feed on itself (a sharper
    kernel leaves fewer normals with posterior mass, whose moments are sharper still) and on
    real pairs it drifted to 5 deg; the assigned normals' spread is what the kernel must
    cover.
    """
    k = len(Cs)
    C = Cs.sum(axis=0)
    weighted, wsum, xsum, ssum = kernels.bin_group_moments(
        assign, t_unit, observed.weights, observed.resultants, observed.scatters.reshape(-1, 9), k
    )
    Bm = weighted.reshape(k, 3, 3)
    g1s, g2s = gamma[:, :, 1], gamma[:, :, 2]
    A = beta[:, None, None] * (
        g2s[:, :, None] * g2s[:, None, :] - g1s[:, :, None] * g1s[:, None, :]
    )
    problem = KentRotationProblem(A, Bm, C)
    mass = np.asarray(np.bincount(assign, weights=tn, minlength=k), dtype=np.float64)
    if rotation == 'shared':
        R_new = _shared_m_step(problem, R)
    else:
        Rs = []
        for j in range(k):
            pj = KentRotationProblem(A[j : j + 1], Bm[j : j + 1], Cs[j])
            Rs.append(solve_kent_rotation(pj, R)[0] if mass[j] > 0.0 else R)
        R_new = average_rotations(np.array(Rs), mass + 1e-12)
    # Kent parameters from the moments of the rotated normals assigned to each cluster.
    has = mass > 1e-9 * max(float(observed.weights.sum()), 1.0)
    if has.any():
        kh, bh, gh = kent_moments_of_sums(wsum[has], xsum[has], ssum[has], rotation=R_new)
        kappa_m[has], beta_m[has], gamma[has] = kh, bh, gh
    return R_new, problem, mass


def _pass_kernels(
    kappa_m: FloatArray, beta_m: FloatArray, cap: float, use_beta: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The kernels of one pass: the model's ``kappa`` capped at ``cap``, ``beta`` scaled with
    it (or zero), and their log normalisers."""
    k = len(kappa_m)
    kappa = np.minimum(kappa_m, cap)
    beta = beta_m * (kappa / np.maximum(kappa_m, 1e-300)) if use_beta else np.zeros(k)
    log_c = np.asarray(kent_log_normalizer(kappa, beta), dtype=np.float64).reshape(k)
    return kappa, beta, log_c


def _settled(history: list[float], small_step: bool, tolerance: float) -> bool:
    """At the final cap: the rotation moved less than ``tolerance``, or the likelihood stalled
    (bins near a cluster boundary can switch clusters back and forth, the likelihood then
    stalls while the rotation jitters by less than the data resolve)."""
    if len(history) < 2:
        return False
    rel = abs(history[-1] - history[-2]) / max(abs(history[-1]), 1e-12)
    return small_step or rel < tolerance


def shared_rotation_em(
    observed: NormalBins,
    model: ModelClusters,
    R0: FloatArray,
    *,
    outlier_weight: float = 0.1,
    use_beta: bool = False,
    rotation: str = 'shared',
    kappa_cap_start: float = 20.0,
    kappa_cap_end: float = 2000.0,
    kappa_cap_growth: float = 2.0,
    max_iterations: int = 50,
    tolerance: float = 1e-6,
) -> EMResult:
    """The paper's Kent mixture likelihood over all clusters, with one shared rotation.

    Parameters
    ----------
    observed : NormalBins
        Observed (source) unit normals, binned.
    model : ModelClusters
        The model (target): its binned normals ``y_m``, partition and Kent parameters.
    R0 : ndarray, shape (3, 3)
        Initial rotation.
    outlier_weight : float
        ``pi0``; the outlier density ``p0`` is uniform on the sphere, ``1 / (4 pi)``.
    use_beta : bool
        Put the Kent ovalness into the E-step kernels as the paper does. Its term
        ``beta [(g1 . R x)^2 - (g2 . R x)^2]`` acts on the observed normal itself, not on its
        deviation from ``y_m``: a cluster-wide prior pulling normals toward the cluster's major
        axis, which biases the rotation wherever a cluster's spread differs between the two
        views (see ``docs/notes-registration.md``). False (default): von Mises-Fisher kernels;
        ``beta`` is estimated and returned either way.
    rotation : {'shared', 'averaged'}
        'averaged' solves each cluster's M-step alone and averages the rotations by the
        paper's eq. rot_avg, weighted by posterior mass (an ablation).
    kappa_cap_start, kappa_cap_end, kappa_cap_growth : float
        The Kent concentrations used in the E-step are capped at ``kappa_cap_start`` in the
        first pass, the cap growing by ``kappa_cap_growth`` per pass up to ``kappa_cap_end``
        (annealing: a wide basin first; ``beta`` is scaled with ``kappa``).
    max_iterations : int
    tolerance : float
        Stop once the cap is at its end and the rotation changes by less than this (rad).

    Notes
    -----
    Each pass is :func:`_shared_e_step` (the posteriors of the observed bins over the model
    bins of their cluster) and :func:`_m_step` (one rotation for all clusters, then every
    cluster's Kent parameters by Kent's moment estimate); their docstrings give the formulas.
    """
    x = observed.directions
    wx = observed.weights
    k = len(model)
    fixed = _ModelTerms.of(model, outlier_weight)
    log_out = np.log(max(outlier_weight, 1e-300)) + LOG_UNIFORM_SPHERE
    kappa_m, beta_m, gamma = model.kappa.copy(), model.beta.copy(), model.gamma.copy()
    R = np.array(R0, dtype=np.float64)
    cap = kappa_cap_start
    history: list[float] = []
    converged = False
    it = 0
    problem = KentRotationProblem(np.zeros((k, 3, 3)), np.zeros((k, 3, 3)), np.zeros((3, 3)))
    tn = np.zeros(len(x))
    mass = np.zeros(k)
    kappa = np.minimum(kappa_m, cap)
    beta = np.zeros(k)
    for it in range(1, max_iterations + 1):
        kappa, beta, log_c = _pass_kernels(kappa_m, beta_m, cap, use_beta)
        z = x @ R.T
        assign = np.argmax(z @ model.centers.T, axis=1)
        Cs, loglik, tn, t_unit = _shared_e_step(
            z, observed, fixed, assign, log_c, kappa, beta, gamma, log_out
        )
        history.append(loglik)
        R_new, problem, mass = _m_step(
            observed, Cs, tn, t_unit, assign, beta, gamma, R, rotation, kappa_m, beta_m
        )
        small_step = _rotation_tolerance_reached(R, R_new, tolerance)
        R = R_new
        at_final_cap = cap >= kappa_cap_end or cap >= float(kappa_m.max())
        if at_final_cap and _settled(history, small_step, tolerance):
            converged = True
            break
        cap = min(cap * kappa_cap_growth, kappa_cap_end)
    return EMResult(
        R=R,
        kappa=kappa_m,
        beta=beta_m,
        log_likelihood=history,
        iterations=it,
        converged=converged,
        inlier_fraction=float(tn.sum() / max(float(wx.sum()), 1e-12)),
        hessian=problem.hessian(R),
    )


def paper_cluster_em(
    y: FloatArray,
    x: FloatArray,
    R0: FloatArray,
    *,
    outlier_weight: float = 0.1,
    max_iterations: int = 50,
    tolerance: float = 1e-6,
) -> EMResult:
    """Algorithm 2 of the paper on one cluster: per-model-normal Kent components.

    Parameters
    ----------
    y : ndarray, shape (M, 3)
        Model unit normals of the cluster (the component means ``y_m``).
    x : ndarray, shape (N, 3)
        Observed unit normals of the paired cluster.
    R0 : ndarray, shape (3, 3)
        Initial rotation.
    outlier_weight : float
        ``pi0``; ``pi_m = (1 - pi0) / M`` and ``p0 = 1 / N`` as in the paper.

    Notes
    -----
    The Kent parameters are initialised by the moment estimate of the rotated observed normals
    ("initialised in the E-step based on the current frame") and updated by the Kent (1982)
    moment estimator from the ``T_n = sum_m tau_mn`` weighted moments. The stop rule is a
    relative change of Q or a rotation change below ``tolerance``.
    """
    m, n = len(y), len(x)
    R = np.array(R0, dtype=np.float64)
    params = fit_kent_moments(x @ R.T)
    kappa, beta, gamma = params.kappa, params.beta, params.gamma
    log_pi = np.log((1.0 - outlier_weight) / m)
    log_out = np.log(max(outlier_weight, 1e-300)) - np.log(n)
    history: list[float] = []
    q_prev: float | None = None
    converged = False
    it = 0
    tau_mass = np.zeros(n)
    problem = KentRotationProblem(np.zeros((1, 3, 3)), np.zeros((1, 3, 3)), np.zeros((3, 3)))
    for it in range(1, max_iterations + 1):
        z = x @ R.T
        g1, g2 = gamma[:, 1], gamma[:, 2]
        qn = (z @ g1) ** 2 - (z @ g2) ** 2
        log_c = float(kent_log_normalizer(kappa, beta))
        logfb5 = -log_c + kappa * (y @ z.T) + beta * qn[None, :]  # (M, N)
        numer = log_pi + logfb5
        log_p = np.logaddexp(logsumexp(numer, axis=0), log_out)
        tau = np.exp(numer - log_p[None, :])
        tau0 = np.maximum(1.0 - tau.sum(axis=0), 0.0)
        history.append(float(log_p.sum()))
        q = float(np.sum(tau * numer) + np.sum(tau0 * log_out))
        # M-step: rotation.
        tau_mass = tau.sum(axis=0)
        A = np.outer(g2, g2) - np.outer(g1, g1)
        Bm = (x * tau_mass[:, None]).T @ x
        C = x.T @ (tau.T @ y)
        problem = KentRotationProblem(beta * A[None], Bm[None], kappa * C)
        start = min([R, procrustes(C)], key=problem.value)
        R_new, _ = solve_kent_rotation(problem, start)
        # M-step: Kent parameters by weighted moments of the rotated normals.
        if tau_mass.sum() > 1e-9:
            params = fit_kent_moments(x @ R_new.T, tau_mass)
            kappa = params.kappa
            beta = min(params.beta, MAX_BETA_RATIO * params.kappa)
            gamma = params.gamma
        small_step = _rotation_tolerance_reached(R, R_new, tolerance)
        R = R_new
        if q_prev is not None:
            rel = abs(q - q_prev) / max(abs(q), 1e-12)
            if rel < tolerance or small_step:
                converged = True
                break
        q_prev = q
    return EMResult(
        R=R,
        kappa=np.array([kappa]),
        beta=np.array([beta]),
        log_likelihood=history,
        iterations=it,
        converged=converged,
        inlier_fraction=float(tau_mass.sum() / max(n, 1)),
        hessian=problem.hessian(R),
    )
