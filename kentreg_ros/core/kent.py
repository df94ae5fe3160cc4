"""The Kent (FB5) distribution on the unit sphere S^2.

Density (Kent 1982, "The Fisher-Bingham distribution on the sphere", JRSS-B 44(1))::

    f(x) = exp(kappa * g1.x + beta * ((g2.x)^2 - (g3.x)^2)) / c(kappa, beta)

with ``Gamma = [g1 g2 g3]`` a rotation (columns: mean direction, major axis, minor axis),
``kappa >= 0`` and ``0 <= beta < kappa / 2`` (the unimodal case; ``kappa = beta = 0`` is the
uniform distribution).

Contents
--------
* :class:`KentParams` -- validated, immutable parameters.
* :func:`kent_log_normalizer` -- ``log c(kappa, beta)``, vectorised, exact up to rounding
  (relative error ~1e-15 in ``log c``) for ``0 <= kappa <= 1e6`` and every ``beta < kappa/2``.
* :func:`kent_log_pdf` -- log density of unit vectors.
* :func:`fit_kent_moments`, :func:`fit_kent_moments_batch` -- Kent's (1982, section 4)
  moment estimator, weighted, vectorised over components.
* :func:`sample_kent` -- an exact acceptance-rejection sampler.

Normaliser
----------
Two exact representations are used, switching at ``kappa = KAPPA_SWITCH``:

* ``kappa <= KAPPA_SWITCH``: Kent's series::

      c = 2 pi sum_j Gamma(j + 1/2) / Gamma(j + 1) beta^(2j) (kappa/2)^(-2j-1/2) I_(2j+1/2)(kappa)

  summed in log space with ``scipy.special.ive`` and ``logsumexp``. The terms decay like
  ``exp(-2 j^2 / kappa)`` even for ``beta -> kappa / 2``, so ``ceil(5 sqrt(kappa) + 10)``
  terms reach double precision; a convergence check guards this.
* ``kappa > KAPPA_SWITCH``: Kent's asymptotic form ``c ~ 2 pi e^kappa / sqrt(kappa^2 -
  4 beta^2)`` times its exact correction factor. With ``u = 1 - g1.x`` and the tangent
  angle ``phi``, ``c = e^kappa int_0^2pi int_0^2 exp(-a u - q u^2) du dphi`` where
  ``a = kappa - 2 beta cos 2phi`` and ``q = beta cos 2phi``. The inner integral has a closed
  form through ``erfcx`` (``q > 0``) or Dawson's function (``q < 0``) up to terms of relative
  size ``exp(-2 kappa)`` (< 1e-43 here), and the outer integral of this smooth periodic
  function is computed by the trapezoidal rule, which converges geometrically; the number of
  nodes follows the angular width of the integrand. The leading term alone is not accurate
  enough: its relative error is about ``6 kappa beta^2 / (kappa^2 - 4 beta^2)^2`` (0.7 % at
  ``kappa = 300, beta = 100``; ~4 in ``log c`` for ``beta -> kappa/2`` even at
  ``kappa = 1e6``).

Both branches agree to ~1e-13 absolute in ``log c`` wherever both are valid
(``kappa >= 20``), so the switch point only trades cost: the series needs ~45 Bessel
evaluations at the switch, the quadrature 32 to a few hundred ``erfcx`` evaluations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import dawsn, erfcx, gammaln, ive, logsumexp, xlogy

from kentreg_ros.core import kernels
from kentreg_ros.core.errors import KentRegError
from kentreg_ros.core.geometry import row_norms

FloatArray = NDArray[np.float64]

#: Largest concentration returned by the moment estimators (degenerate samples).
KAPPA_MAX = 1e6
#: Estimated ``beta`` is clipped to ``MAX_BETA_RATIO * kappa`` (strictly unimodal).
MAX_BETA_RATIO = 0.499
#: ``kent_log_normalizer`` uses Kent's series for ``kappa <= KAPPA_SWITCH``, quadrature above.
KAPPA_SWITCH = 50.0

_LOG_2PI = math.log(2.0 * math.pi)
_LOG_4PI = math.log(4.0 * math.pi)
_SERIES_LOG_TOL = -40.0  # last series term must be < e^-40 (~4e-18) of the sum
_QUAD_MIN_NODES = 32
_QUAD_MAX_NODES = 1 << 15
_QUAD_WIDTH_NODES = 16.0  # nodes per angular width of the integrand
_QUAD_CHUNK = 1 << 20  # maximum elements of one (components x nodes) block
_ORTHO_TOL = 1e-6


class KentError(KentRegError, ValueError):
    """Invalid Kent parameters or inputs to the Kent routines."""


def _check_kappa_beta(kappa: FloatArray, beta: FloatArray) -> None:
    """Raise :class:`KentError` unless ``0 <= beta < kappa / 2`` or ``kappa = beta = 0``."""
    finite = np.isfinite(kappa) & np.isfinite(beta)
    ok = finite & (kappa >= 0.0) & (beta >= 0.0) & ((beta < 0.5 * kappa) | (kappa == 0.0))
    ok &= ~((kappa == 0.0) & (beta != 0.0))
    if not np.all(ok):
        idx = np.unravel_index(int(np.argmin(ok)), ok.shape)
        k, b = float(kappa[idx]), float(beta[idx])
        raise KentError(
            'Expected finite 0 <= beta < kappa / 2 (unimodal Kent; kappa = beta = 0 allowed), '
            f'got kappa={k!r}, beta={b!r}.'
        )


@dataclass(frozen=True, eq=False)
class KentParams:
    """Parameters of one Kent distribution (immutable; compared by identity).

    Parameters
    ----------
    kappa : float
        Concentration, ``>= 0``.
    beta : float
        Ovalness, ``0 <= beta < kappa / 2`` (``beta = 0`` if ``kappa = 0``).
    gamma : ndarray, shape (3, 3)
        Rotation matrix (orthonormal, det +1) with columns mean direction, major axis,
        minor axis. Stored as a read-only float64 copy.

    Raises
    ------
    KentError
        Parameters outside the unimodal range, or ``gamma`` not a rotation (tolerance 1e-6).
    """

    kappa: float
    beta: float
    gamma: FloatArray = field(repr=False)

    def __post_init__(self) -> None:
        try:
            kappa = float(self.kappa)
            beta = float(self.beta)
        except (TypeError, ValueError) as exc:
            raise KentError(f'Expected numeric `kappa` and `beta`, got {exc}.') from exc
        _check_kappa_beta(np.asarray(kappa), np.asarray(beta))
        try:
            gamma = np.array(self.gamma, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise KentError(f'Expected `gamma` to be a numeric (3, 3) array, got {exc}.') from exc
        if gamma.shape != (3, 3) or not np.all(np.isfinite(gamma)):
            raise KentError(f'Expected `gamma` to be a finite (3, 3) array, got {gamma.shape}.')
        ortho_err = float(np.max(np.abs(gamma.T @ gamma - np.eye(3))))
        det = float(np.linalg.det(gamma))
        if ortho_err > _ORTHO_TOL or det <= 0.0:
            raise KentError(
                'Expected `gamma` to be a rotation matrix (orthonormal, det +1), got '
                f'max |G^T G - I| = {ortho_err:.3g}, det = {det:.6g}.'
            )
        gamma.flags.writeable = False
        object.__setattr__(self, 'kappa', kappa)
        object.__setattr__(self, 'beta', beta)
        object.__setattr__(self, 'gamma', gamma)

    @property
    def mean(self) -> FloatArray:
        """Mean direction ``gamma[:, 0]``, shape (3,)."""
        return self.gamma[:, 0]

    @property
    def major(self) -> FloatArray:
        """Major axis ``gamma[:, 1]`` (direction of largest spread), shape (3,)."""
        return self.gamma[:, 1]

    @property
    def minor(self) -> FloatArray:
        """Minor axis ``gamma[:, 2]``, shape (3,)."""
        return self.gamma[:, 2]


# --------------------------------------------------------------------------------------------
# Normalising constant
# --------------------------------------------------------------------------------------------


def _series_n_terms(kappa_max: float) -> int:
    """Number of series terms reaching double precision for every ``kappa <= kappa_max``."""
    return int(math.ceil(5.0 * math.sqrt(kappa_max) + 10.0))


def _log_normalizer_series(kappa: FloatArray, beta: FloatArray) -> FloatArray:
    """Kent's series for ``log c``; ``kappa`` (M,) > 0, ``beta`` (M,) -> (M,).

    Raises
    ------
    RuntimeError
        The series did not converge to double precision (cannot happen for
        ``kappa <= KAPPA_SWITCH``; guards misuse).
    """
    if kappa.size == 0:
        return np.zeros(0)
    j = np.arange(_series_n_terms(float(np.max(kappa))), dtype=np.float64)
    nu = 2.0 * j + 0.5
    k = kappa[:, None]
    with np.errstate(divide='ignore'):  # ive underflows to 0 for orders >> kappa
        log_terms = (
            gammaln(j + 0.5)
            - gammaln(j + 1.0)
            + xlogy(2.0 * j, beta[:, None])
            - nu * np.log(0.5 * k)
            + np.log(ive(nu, k))
            + k
        )
    total = logsumexp(log_terms, axis=1)
    if np.any(log_terms[:, -1] - total > _SERIES_LOG_TOL):
        raise RuntimeError('Kent normaliser series did not converge; kappa too large.')
    return np.asarray(_LOG_2PI + total, dtype=np.float64)


def _laplace_factor(y: FloatArray) -> FloatArray:
    """``H(y) = int_0^inf exp(-s - y s^2) ds`` (for ``y < 0`` the asymptotic value).

    ``y > 0``: ``sqrt(pi) z erfcx(z)``; ``y < 0``: ``2 z D(z)`` with Dawson's ``D``;
    ``z = 1 / (2 sqrt|y|)``; ``1 - 2y + 12y^2`` for ``|y| < 1e-12``.
    """
    small = np.abs(y) < 1e-12
    z = 0.5 / np.sqrt(np.where(small, 1.0, np.abs(y)))
    closed = np.where(y > 0.0, math.sqrt(math.pi) * z * erfcx(z), 2.0 * z * dawsn(z))
    return np.where(small, 1.0 - 2.0 * y + 12.0 * y * y, closed)


def _quadrature_n_nodes(kappa: FloatArray, beta: FloatArray) -> int:
    """Trapezoid nodes on ``psi = 2 phi in [0, pi]`` resolving the narrowest integrand."""
    pos = beta > 0.0
    if not np.any(pos):
        return _QUAD_MIN_NODES
    k, b = kappa[pos], beta[pos]
    # Angular half-width of G(psi) around psi = 0: a(psi) ~ (kappa - 2 beta) + beta psi^2.
    width = np.sqrt(np.maximum(k - 2.0 * b, np.sqrt(b)) / b)
    n = int(math.ceil(_QUAD_WIDTH_NODES / float(np.min(width))))
    n = -(-n // 16) * 16
    return min(max(n, _QUAD_MIN_NODES), _QUAD_MAX_NODES)


def _log_normalizer_quadrature(kappa: FloatArray, beta: FloatArray) -> FloatArray:
    """Large-kappa ``log c`` by angular quadrature; ``kappa`` (M,) > ~20 -> (M,).

    ``c = 2 pi e^kappa mean_psi G(psi)``, ``G = H(q / a^2) / a``, ``a = kappa - 2 beta cos psi``,
    ``q = beta cos psi``; midpoint nodes on ``[0, pi]`` equal the periodic trapezoidal rule.
    Terms of relative size ``exp(-2 kappa)`` are neglected.
    """
    out = np.empty_like(kappa)
    if kappa.size == 0:
        return out
    n_nodes = _quadrature_n_nodes(kappa, beta)
    cos_psi = np.cos((np.arange(n_nodes) + 0.5) * (math.pi / n_nodes))
    rows = max(1, _QUAD_CHUNK // n_nodes)
    for start in range(0, kappa.size, rows):  # bounded memory: loop over blocks of components
        k = kappa[start : start + rows, None]
        b = beta[start : start + rows, None]
        a = k - 2.0 * b * cos_psi
        g = _laplace_factor(b * cos_psi / (a * a)) / a
        out[start : start + rows] = _LOG_2PI + k[:, 0] + np.log(np.mean(g, axis=1))
    return out


def kent_log_normalizer(kappa: ArrayLike, beta: ArrayLike) -> FloatArray | float:
    """Log normalising constant ``log c(kappa, beta)`` of the Kent distribution.

    ``c = int_{S^2} exp(kappa g1.x + beta ((g2.x)^2 - (g3.x)^2)) dx``. Special cases:
    ``c(0, 0) = 4 pi`` and ``c(kappa, 0) = 4 pi sinh(kappa) / kappa`` (von Mises-Fisher).
    Exact up to rounding (relative error ~1e-15 in ``log c``) for any ``kappa`` up to at least
    1e6; see the module docstring.

    Parameters
    ----------
    kappa : array_like, shape (...)
        Concentrations, ``>= 0``.
    beta : array_like, shape (...)
        Ovalness, broadcast against ``kappa``; ``0 <= beta < kappa / 2`` (``kappa = beta = 0``
        allowed).

    Returns
    -------
    ndarray or float
        ``log c`` with the broadcast shape; a Python float if both inputs are scalars.

    Raises
    ------
    KentError
        Negative or non-finite values, or ``beta >= kappa / 2`` (a ``ValueError``).
    """
    try:
        k_arr, b_arr = np.broadcast_arrays(
            np.asarray(kappa, dtype=np.float64), np.asarray(beta, dtype=np.float64)
        )
    except (TypeError, ValueError) as exc:
        raise KentError(f'Expected numeric, broadcastable `kappa` and `beta`, got {exc}.') from exc
    _check_kappa_beta(k_arr, b_arr)
    k = k_arr.ravel()
    b = b_arr.ravel()
    out = np.full(k.shape, _LOG_4PI)
    # beta = 0 is von Mises-Fisher, in closed form: log(4 pi sinh(k) / k)
    # = log(2 pi / k) + k + log(1 - exp(-2 k)).
    vmf = (k > 0.0) & (b == 0.0)
    kv = k[vmf]
    out[vmf] = np.log(2.0 * np.pi / kv) + kv + np.log(-np.expm1(-2.0 * kv))
    series = (k > 0.0) & (k <= KAPPA_SWITCH) & ~vmf
    quad = (k > KAPPA_SWITCH) & ~vmf
    out[series] = _log_normalizer_series(k[series], b[series])
    out[quad] = _log_normalizer_quadrature(k[quad], b[quad])
    if k_arr.ndim == 0:
        return float(out[0])
    return out.reshape(k_arr.shape)


# --------------------------------------------------------------------------------------------
# Density
# --------------------------------------------------------------------------------------------


def _as_vectors(x: ArrayLike, name: str) -> FloatArray:
    """Validate ``x`` as a finite float64 array of shape (N, 3) with N >= 1."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KentError(f'Expected `{name}` to be numeric, got {exc}.') from exc
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
        raise KentError(f'Expected `{name}` to have shape (N, 3) with N >= 1, got {arr.shape}.')
    if not np.all(np.isfinite(arr)):
        raise KentError(f'Expected `{name}` to be finite, got NaN or inf entries.')
    return arr


def kent_log_pdf(x: ArrayLike, params: KentParams) -> FloatArray:
    """Log density of the Kent distribution (w.r.t. the surface measure of S^2).

    Parameters
    ----------
    x : array_like, shape (N, 3)
        Unit vectors (not re-normalised).
    params : KentParams

    Returns
    -------
    ndarray, shape (N,)
        ``kappa g1.x + beta ((g2.x)^2 - (g3.x)^2) - log c(kappa, beta)``.

    Raises
    ------
    KentError
        ``x`` is not a finite (N, 3) array.
    """
    u = _as_vectors(x, 'x') @ params.gamma
    log_c = float(kent_log_normalizer(params.kappa, params.beta))
    return np.asarray(
        params.kappa * u[:, 0] + params.beta * (u[:, 1] ** 2 - u[:, 2] ** 2) - log_c,
        dtype=np.float64,
    )


# --------------------------------------------------------------------------------------------
# Moment estimation
# --------------------------------------------------------------------------------------------


def _as_unit_vectors(x: ArrayLike) -> FloatArray:
    """Validate ``x`` (N, 3) and normalise its rows; zero rows raise :class:`KentError`."""
    arr = _as_vectors(x, 'x')
    norms = row_norms(arr)
    if np.any(norms <= 0.0):
        raise KentError(
            f'Expected `x` rows to be non-zero vectors, got {int(np.sum(norms <= 0.0))} zero rows.'
        )
    return arr / norms[:, None]


def _as_weights(weights: ArrayLike, n: int, *, batch: bool) -> FloatArray:
    """Validate finite non-negative weights of shape (K, n) if ``batch`` else (n,)."""
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KentError(f'Expected `weights` to be numeric, got {exc}.') from exc
    if batch and (w.ndim != 2 or w.shape[1] != n):
        raise KentError(f'Expected `weights` to have shape (K, {n}), got {w.shape}.')
    if not batch and w.shape != (n,):
        raise KentError(f'Expected `weights` to have shape ({n},), got {w.shape}.')
    if not np.all(np.isfinite(w)):
        raise KentError('Expected `weights` to be finite, got NaN or inf entries.')
    if np.any(w < 0.0):
        raise KentError(f'Expected `weights` to be non-negative, got minimum {float(w.min())!r}.')
    return w


def fit_kent_moments_batch(
    x: ArrayLike, weights: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Kent (1982, section 4) moment estimates for K weighted components at once.

    For each component, with weighted mean ``xbar`` and scatter ``S = sum w x x^T / sum w``:
    ``H`` rotates the first axis onto ``xbar / |xbar|``; the tangent 2x2 block of
    ``H^T S H`` is diagonalised by a rotation ``psi`` so that ``gamma1`` (column 1) is the axis
    of larger spread; ``r1 = |xbar|``, ``r2 = l1 - l2`` (tangent eigenvalue gap) and::

        kappa = 1 / (2 - 2 r1 - r2) + 1 / (2 - 2 r1 + r2)
        beta = (1 / (2 - 2 r1 - r2) - 1 / (2 - 2 r1 + r2)) / 2

    ``kappa`` is clipped to :data:`KAPPA_MAX` (e.g. identical vectors) and ``beta`` to
    ``MAX_BETA_RATIO * kappa``. When ``1 - r1`` is at rounding level (< 1.4e-14) the ratio
    ``beta / kappa`` is noise and is set to 0. A component whose weights are all zero (maximum
    below the smallest normal float) gets ``kappa = 0``, ``beta = 0``, ``gamma = I``.
    The estimate is invariant to the scale of each weight row.

    Parameters
    ----------
    x : array_like, shape (N, 3)
        Directions; rows are normalised to unit length.
    weights : array_like, shape (K, N)
        Non-negative finite weights per component.

    Returns
    -------
    kappa : ndarray, shape (K,)
    beta : ndarray, shape (K,)
    gamma : ndarray, shape (K, 3, 3)
        Rotations (det +1) with columns mean, major axis, minor axis.

    Raises
    ------
    KentError
        Malformed ``x`` (shape, non-finite, zero rows) or ``weights`` (shape, negative,
        non-finite).
    """
    xu = _as_unit_vectors(x)
    n = xu.shape[0]
    w = _as_weights(weights, n, batch=True)
    k_comp = w.shape[0]
    if k_comp == 0:
        return np.zeros(0), np.zeros(0), np.zeros((0, 3, 3))

    w_max = np.max(w, axis=1)
    degenerate = ~(w_max >= np.finfo(np.float64).tiny)
    w = w / np.where(degenerate, 1.0, w_max)[:, None]
    w_sum = np.where(degenerate, 1.0, np.sum(w, axis=1))
    outer = (xu[:, :, None] * xu[:, None, :]).reshape(n, 9)
    xbar = (w @ xu) / w_sum[:, None]
    scatter = ((w @ outer) / w_sum[:, None]).reshape(k_comp, 3, 3)
    kappa, beta, gamma = kent_from_moments(xbar, scatter)
    kappa[degenerate] = 0.0
    beta[degenerate] = 0.0
    gamma[degenerate] = np.eye(3)
    return kappa, beta, gamma


def kent_from_moments(
    xbar: FloatArray, scatter: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Kent's (1982, section 4) moment estimates from first and second sample moments.

    With ``xbar`` the (weighted) mean vector and ``S`` the (weighted) mean of ``x x^T``:
    ``H`` rotates the first axis onto ``xbar / |xbar|``; the tangent 2x2 block of ``H^T S H``
    is diagonalised by a rotation ``psi`` so that ``gamma1`` is the axis of larger spread;
    with ``r1 = |xbar|`` and ``r2 = l1 - l2`` (the tangent eigenvalue gap)::

        kappa = 1 / (2 - 2 r1 - r2) + 1 / (2 - 2 r1 + r2)
        beta  = (1 / (2 - 2 r1 - r2) - 1 / (2 - 2 r1 + r2)) / 2

    i.e. ``kappa - 2 beta = 1 / (2 - 2 r1 + r2)`` and ``kappa + 2 beta = 1 / (2 - 2 r1 - r2)``,
    the precisions along the major and the minor axis: ``beta > 0`` exactly when the spread
    along the major axis exceeds that along the minor one.

    Parameters
    ----------
    xbar : ndarray, shape (K, 3)
    scatter : ndarray, shape (K, 3, 3)

    Returns
    -------
    kappa, beta : ndarray, shape (K,)
        ``kappa`` clipped to :data:`KAPPA_MAX`, ``beta`` to ``MAX_BETA_RATIO * kappa``.
    gamma : ndarray, shape (K, 3, 3)
        Rotations (det +1) with columns mean, major axis, minor axis.
    """
    return kernels.kent_from_moments(xbar, scatter, KAPPA_MAX, MAX_BETA_RATIO)


def fit_kent_moments(x: ArrayLike, weights: ArrayLike | None = None) -> KentParams:
    """Kent (1982) moment estimate of one Kent distribution from weighted unit vectors.

    See :func:`fit_kent_moments_batch` (this is its ``K = 1`` case).

    Parameters
    ----------
    x : array_like, shape (N, 3)
        Directions, N >= 1; rows are normalised to unit length.
    weights : array_like, shape (N,), optional
        Non-negative finite weights, not all zero. Default: equal weights.

    Returns
    -------
    KentParams

    Raises
    ------
    KentError
        Malformed ``x`` or ``weights`` (wrong shape, negative, non-finite, all zero).
    """
    xu = _as_vectors(x, 'x')
    n = xu.shape[0]
    w = np.ones(n) if weights is None else _as_weights(weights, n, batch=False)
    if not np.any(w > 0.0):
        raise KentError(f'Expected `weights` to contain a positive value, got all {n} zero.')
    kappa, beta, gamma = fit_kent_moments_batch(xu, w[None, :])
    return KentParams(float(kappa[0]), float(beta[0]), gamma[0])
