"""Tests of kentreg_ros.core.kent: normaliser, density, moment estimator and sampler."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from kentreg_ros.core import KentRegError, kent, kent_sampling
from kentreg_ros.core.kent import (
    KAPPA_MAX,
    KAPPA_SWITCH,
    MAX_BETA_RATIO,
    KentError,
    KentParams,
    fit_kent_moments,
    fit_kent_moments_batch,
    kent_log_normalizer,
    kent_log_pdf,
)
from kentreg_ros.core.kent_sampling import sample_kent

FloatArray = NDArray[np.float64]


def _random_rotation(rng: np.random.Generator) -> FloatArray:
    """Uniformly random rotation (QR of a Gaussian matrix, det fixed to +1)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 2] = -q[:, 2]
    return q


def _log_vmf(kappa: float) -> float:
    """log(4 pi sinh(kappa) / kappa), stable for large kappa."""
    return math.log(2.0 * math.pi) + kappa + math.log(-math.expm1(-2.0 * kappa)) - math.log(kappa)


def _log_c_by_sphere_quadrature(
    kappa: float, beta: float, n_u: int = 400, n_phi: int = 256
) -> float:
    """log c by direct 2-D quadrature over the sphere in the Gamma frame (independent check).

    Coordinates u = g1.x (Gauss-Legendre on [u0, 1], where the density beyond u0 is below
    e^-60 of the peak) and the angle phi around g1 (periodic trapezoid); dS = du dphi.
    """
    u0 = max(-1.0, 1.0 - 60.0 / max(kappa - 2.0 * beta, 1e-300))
    t, w = np.polynomial.legendre.leggauss(n_u)
    u = 0.5 * (1.0 - u0) * t + 0.5 * (1.0 + u0)
    wu = 0.5 * (1.0 - u0) * w
    phi = 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    sin2 = 1.0 - u[:, None] ** 2
    expo = kappa * (u[:, None] - 1.0) + beta * sin2 * np.cos(2.0 * phi[None, :])
    integral = float(np.sum(wu[:, None] * np.exp(expo)) * 2.0 * np.pi / n_phi)
    return kappa + math.log(integral)


def _world_sphere_grid(n_z: int, n_phi: int) -> tuple[FloatArray, FloatArray]:
    """Points (n_z * n_phi, 3) and quadrature weights of a Gauss-Legendre x trapezoid grid."""
    z, wz = np.polynomial.legendre.leggauss(n_z)
    phi = 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    rho = np.sqrt(1.0 - z**2)
    pts = np.stack(
        [
            (rho[:, None] * np.cos(phi)[None, :]).ravel(),
            (rho[:, None] * np.sin(phi)[None, :]).ravel(),
            np.repeat(z, n_phi),
        ],
        axis=1,
    )
    weights = np.repeat(wz, n_phi) * (2.0 * np.pi / n_phi)
    return pts, weights


def _log_c_derivatives(kappa: float, beta: float) -> tuple[float, float]:
    """(d log c / d kappa, d log c / d beta) = (E[g1.x], E[(g2.x)^2 - (g3.x)^2])."""
    h = 1e-5 * max(kappa, 1.0)
    dk = (
        float(kent_log_normalizer(kappa + h, beta)) - float(kent_log_normalizer(kappa - h, beta))
    ) / (2.0 * h)
    hb = min(h, 0.25 * (0.5 * kappa - beta))
    if beta >= hb:
        db = (
            float(kent_log_normalizer(kappa, beta + hb))
            - float(kent_log_normalizer(kappa, beta - hb))
        ) / (2.0 * hb)
    else:
        db = (
            float(kent_log_normalizer(kappa, beta + hb)) - float(kent_log_normalizer(kappa, beta))
        ) / hb
    return dk, db


def _population_moment_estimate(kappa: float, beta: float) -> tuple[float, float]:
    """Kent's moment estimator applied to the exact population moments (its large-N limit)."""
    r1, r2 = _log_c_derivatives(kappa, beta)
    d_minus, d_plus = 2.0 - 2.0 * r1 - r2, 2.0 - 2.0 * r1 + r2
    return 1.0 / d_minus + 1.0 / d_plus, 0.5 * (1.0 / d_minus - 1.0 / d_plus)


def _angle_deg(a: FloatArray, b: FloatArray, *, axial: bool = False) -> float:
    c = float(np.dot(a, b))
    if axial:
        c = abs(c)
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


# --------------------------------------------------------------------------------------------
# Normaliser
# --------------------------------------------------------------------------------------------


def test_log_normalizer_kappa_zero_is_log_4pi() -> None:
    assert kent_log_normalizer(0.0, 0.0) == pytest.approx(math.log(4.0 * math.pi), abs=1e-15)


@pytest.mark.parametrize('kappa', [1e-12, 0.1, 1.0, 10.0, 100.0, 700.0, 1e5])
def test_log_normalizer_beta_zero_equals_von_mises_fisher(kappa: float) -> None:
    assert kent_log_normalizer(kappa, 0.0) == pytest.approx(_log_vmf(kappa), rel=1e-13, abs=1e-13)


@pytest.mark.parametrize(
    ('kappa', 'beta'),
    [(2.0, 0.5), (10.0, 4.0), (50.0, 20.0), (40.0, 19.99), (300.0, 120.0), (900.0, 449.0)],
)
def test_log_normalizer_matches_direct_sphere_quadrature(kappa: float, beta: float) -> None:
    expected = _log_c_by_sphere_quadrature(kappa, beta)
    assert kent_log_normalizer(kappa, beta) == pytest.approx(expected, abs=1e-10)


@pytest.mark.parametrize('ratio', [0.0, 0.1, 0.3, 0.45, 0.499, 0.4999999])
def test_log_normalizer_branches_agree_around_switch(ratio: float) -> None:
    kappa = np.array([20.0, 0.5 * KAPPA_SWITCH, KAPPA_SWITCH, 2.0 * KAPPA_SWITCH, 300.0])
    beta = ratio * kappa
    series = kent._log_normalizer_series(kappa, beta)
    quadrature = kent._log_normalizer_quadrature(kappa, beta)
    np.testing.assert_allclose(quadrature, series, rtol=1e-13, atol=1e-12)
    # The public function is continuous across the switch (to its O(1e-10) slope * step).
    eps = 1e-12 * KAPPA_SWITCH
    k2 = np.array([KAPPA_SWITCH - eps, KAPPA_SWITCH + eps])
    v = kent_log_normalizer(k2, ratio * KAPPA_SWITCH)
    assert isinstance(v, np.ndarray)
    assert abs(v[1] - v[0]) < 1e-9
    assert abs(v[1] - v[0]) / abs(v[0]) < 1e-6


@pytest.mark.parametrize('kappa', [1e4, 1e5, 1e6])
@pytest.mark.parametrize('ratio', [0.0, 0.1, 0.3, 0.45])
def test_log_normalizer_large_kappa_matches_kent_asymptotic_expansion(
    kappa: float, ratio: float
) -> None:
    # log c = log(2 pi e^k / sqrt(k^2 - 4 b^2)) - 6 k b^2 / (k^2 - 4 b^2)^2 + O(k^-2): the
    # quadrature branch reproduces Kent's leading term and the first correction, with a
    # residual smaller than the first correction by a factor O(1 / kappa).
    beta = ratio * kappa
    disc = (kappa - 2.0 * beta) * (kappa + 2.0 * beta)
    leading = math.log(2.0 * math.pi) + kappa - 0.5 * math.log(disc)
    first_order = -6.0 * kappa * beta**2 / disc**2
    got = float(kent_log_normalizer(kappa, beta))
    assert got - leading == pytest.approx(first_order, abs=300.0 * abs(first_order) / kappa + 2e-9)


def test_log_normalizer_finite_and_monotone_up_to_1e6() -> None:
    kappa = np.geomspace(1e-3, 1e6, 60)
    for ratio in [0.0, 0.25, 0.49, 0.4999999]:
        values = kent_log_normalizer(kappa, ratio * kappa)
        assert isinstance(values, np.ndarray)
        assert np.all(np.isfinite(values))
        assert np.all(np.diff(values) > 0.0)
    # Increasing in beta at fixed kappa (d log c / d beta = E[(g2.x)^2 - (g3.x)^2] > 0).
    for k in [0.5, 30.0, 1e3, 1e6]:
        v = kent_log_normalizer(k, np.linspace(0.0, 0.4999 * k, 20))
        assert np.all(np.diff(v) > 0.0)


def test_log_normalizer_broadcasts_and_returns_float_for_scalars() -> None:
    scalar = kent_log_normalizer(10.0, 2.0)
    assert isinstance(scalar, float)
    grid = kent_log_normalizer(np.array([[10.0], [400.0]]), np.array([0.0, 2.0, 4.0]))
    assert isinstance(grid, np.ndarray)
    assert grid.shape == (2, 3)
    assert grid[0, 1] == pytest.approx(scalar, abs=1e-14)
    assert kent_log_normalizer(np.zeros(0), 0.0).shape == (0,)


@pytest.mark.parametrize(
    ('kappa', 'beta'),
    [
        (1.0, 0.5),
        (1.0, 0.7),
        (-1.0, 0.0),
        (1.0, -0.1),
        (0.0, 0.1),
        (float('nan'), 0.0),
        (float('inf'), 1.0),
    ],
)
def test_log_normalizer_rejects_invalid_parameters(kappa: float, beta: float) -> None:
    with pytest.raises(ValueError, match=r'0 <= beta < kappa / 2'):
        kent_log_normalizer(kappa, beta)
    with pytest.raises(KentRegError):
        kent_log_normalizer(np.array([5.0, kappa]), np.array([1.0, beta]))


# --------------------------------------------------------------------------------------------
# Parameters and density
# --------------------------------------------------------------------------------------------


def test_kent_params_validates_and_exposes_axes() -> None:
    gamma = _random_rotation(np.random.default_rng(1))
    params = KentParams(10, 3, gamma)
    assert isinstance(params.kappa, float)
    np.testing.assert_array_equal(params.mean, gamma[:, 0])
    np.testing.assert_array_equal(params.major, gamma[:, 1])
    np.testing.assert_array_equal(params.minor, gamma[:, 2])
    assert not params.gamma.flags.writeable
    with pytest.raises(ValueError, match=r'beta < kappa / 2'):
        KentParams(10.0, 5.0, gamma)
    reflection = gamma * np.array([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match=r'rotation matrix'):
        KentParams(10.0, 3.0, reflection)
    with pytest.raises(ValueError, match=r'rotation matrix'):
        KentParams(10.0, 3.0, 2.0 * gamma)
    with pytest.raises(ValueError, match=r'\(3, 3\)'):
        KentParams(10.0, 3.0, np.eye(2))


def test_kent_log_pdf_integrates_to_one() -> None:
    params = KentParams(30.0, 12.0, _random_rotation(np.random.default_rng(2)))
    pts, weights = _world_sphere_grid(400, 400)
    total = float(np.sum(weights * np.exp(kent_log_pdf(pts, params))))
    assert total == pytest.approx(1.0, abs=1e-10)


def test_kent_log_pdf_uniform_and_shape() -> None:
    x = np.random.default_rng(3).standard_normal((5, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    out = kent_log_pdf(x, KentParams(0.0, 0.0, np.eye(3)))
    assert out.shape == (5,)
    np.testing.assert_allclose(out, -math.log(4.0 * math.pi), atol=1e-15)
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        kent_log_pdf(np.ones((4, 2)), KentParams(1.0, 0.0, np.eye(3)))


# --------------------------------------------------------------------------------------------
# Sampler
# --------------------------------------------------------------------------------------------


def test_sample_kent_unit_norm_shape_and_seeded() -> None:
    params = KentParams(50.0, 10.0, _random_rotation(np.random.default_rng(4)))
    x = sample_kent(params, 1000, rng=5)
    assert x.shape == (1000, 3)
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), 1.0, atol=1e-14)
    np.testing.assert_array_equal(x, sample_kent(params, 1000, rng=np.random.default_rng(5)))
    assert sample_kent(params, 0, rng=5).shape == (0, 3)
    with pytest.raises(ValueError, match=r'`n` >= 0'):
        sample_kent(params, -1)
    with pytest.raises(ValueError, match=r'integer'):
        sample_kent(params, 2.5)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ('kappa', 'beta', 'seed'), [(50.0, 10.0, 10), (200.0, 80.0, 11), (20.0, 0.0, 12)]
)
def test_fit_of_samples_recovers_parameters(kappa: float, beta: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    params = KentParams(kappa, beta, _random_rotation(rng))
    fit = fit_kent_moments(sample_kent(params, 20000, rng=rng))
    # Kent's moment estimator is biased for beta > 0 (its large-N limit is ~4 % low in kappa
    # and ~8 % low in beta at these parameters), hence the tolerances.
    assert fit.kappa == pytest.approx(kappa, rel=0.07)
    if beta > 0.0:
        assert fit.beta == pytest.approx(beta, rel=0.15)
        assert _angle_deg(fit.major, params.major, axial=True) < 3.0
        # Tight check against the estimator's large-N limit (sampling noise ~1 %).
        kappa_lim, beta_lim = _population_moment_estimate(kappa, beta)
        assert fit.kappa == pytest.approx(kappa_lim, rel=0.03)
        assert fit.beta == pytest.approx(beta_lim, rel=0.06)
    else:
        assert fit.beta < 0.02 * kappa
    assert _angle_deg(fit.mean, params.mean) < 1.0
    assert np.linalg.det(fit.gamma) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize(
    ('kappa', 'beta'),
    [(1.0, 0.45), (5.0, 0.0), (50.0, 10.0), (200.0, 80.0), (2000.0, 999.0)],
)
def test_sample_moments_match_normalizer_derivatives(kappa: float, beta: float) -> None:
    # E[g1.x] = d log c / d kappa, E[(g2.x)^2 - (g3.x)^2] = d log c / d beta: checks the
    # sampler's exactness and the normaliser together (z-scores of 20k-sample means).
    rng = np.random.default_rng(int(kappa * 7 + beta))
    params = KentParams(kappa, beta, _random_rotation(rng))
    u = sample_kent(params, 20000, rng=rng) @ params.gamma
    s1 = u[:, 0]
    s2 = u[:, 1] ** 2 - u[:, 2] ** 2
    e1, e2 = _log_c_derivatives(kappa, beta)
    n = len(u)
    assert abs(s1.mean() - e1) < 4.5 * s1.std() / math.sqrt(n)
    assert abs(s2.mean() - e2) < 4.5 * s2.std() / math.sqrt(n)
    # The log-likelihood of the samples matches its expectation kappa E1 + beta E2 - log c.
    ll = kent_log_pdf(u @ params.gamma.T, params)
    expected_ll = kappa * e1 + beta * e2 - float(kent_log_normalizer(kappa, beta))
    assert abs(ll.mean() - expected_ll) < 4.5 * ll.std() / math.sqrt(n)


@pytest.mark.parametrize(
    ('kappa', 'beta', 'min_rate'),
    [
        (0.0, 0.0, 0.7),
        (1.0, 0.49, 0.5),
        (20.0, 0.0, 0.95),
        (2000.0, 0.0, 0.95),
        (2000.0, 999.999, 0.5),
        (1e5, 4.9e4, 0.5),
    ],
)
def test_sampler_acceptance_rate_is_reasonable(kappa: float, beta: float, min_rate: float) -> None:
    samples, rate = kent_sampling._sample_kent_frame(kappa, beta, 5000, np.random.default_rng(6))
    assert samples.shape == (5000, 3)
    assert rate > min_rate


# --------------------------------------------------------------------------------------------
# Moment estimator
# --------------------------------------------------------------------------------------------


def _kent_sample(kappa: float, beta: float, n: int, seed: int) -> FloatArray:
    rng = np.random.default_rng(seed)
    return sample_kent(KentParams(kappa, beta, _random_rotation(rng)), n, rng=rng)


def _assert_same_params(a: KentParams, b: KentParams) -> None:
    assert a.kappa == pytest.approx(b.kappa, rel=1e-9)
    assert a.beta == pytest.approx(b.beta, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(a.gamma, b.gamma, atol=1e-9)


def test_weighted_fit_with_zeroed_half_equals_fit_of_other_half() -> None:
    x = np.concatenate([_kent_sample(40.0, 12.0, 500, 20), _kent_sample(5.0, 1.0, 500, 21)])
    weights = np.concatenate([np.ones(500), np.zeros(500)])
    _assert_same_params(fit_kent_moments(x, weights), fit_kent_moments(x[:500]))
    # Weight scale is irrelevant.
    _assert_same_params(fit_kent_moments(x, 1e-30 * weights), fit_kent_moments(x[:500]))


def test_fit_normalises_rows() -> None:
    x = _kent_sample(30.0, 8.0, 300, 22)
    scale = np.random.default_rng(23).uniform(0.1, 10.0, (300, 1))
    _assert_same_params(fit_kent_moments(scale * x), fit_kent_moments(x))


def test_batch_fit_equals_separate_fits() -> None:
    x = np.concatenate([_kent_sample(60.0, 25.0, 400, 30), _kent_sample(15.0, 3.0, 400, 31)])
    rng = np.random.default_rng(32)
    weights = np.stack(
        [
            rng.uniform(0.0, 1.0, 800),
            np.r_[np.ones(400), np.zeros(400)],
            np.r_[np.zeros(400), rng.uniform(0.0, 5.0, 400)],
        ]
    )
    kappa, beta, gamma = fit_kent_moments_batch(x, weights)
    assert kappa.shape == (3,) and beta.shape == (3,) and gamma.shape == (3, 3, 3)
    for k in range(3):
        _assert_same_params(
            KentParams(kappa[k], beta[k], gamma[k]), fit_kent_moments(x, weights[k])
        )
    np.testing.assert_allclose(np.linalg.det(gamma), 1.0, atol=1e-12)


def test_batch_fit_zero_weight_component_is_degenerate() -> None:
    x = _kent_sample(30.0, 5.0, 100, 33)
    weights = np.stack([np.ones(100), np.zeros(100)])
    kappa, beta, gamma = fit_kent_moments_batch(x, weights)
    assert kappa[1] == 0.0 and beta[1] == 0.0
    np.testing.assert_array_equal(gamma[1], np.eye(3))
    assert kappa[0] > 10.0
    k0, b0, g0 = fit_kent_moments_batch(x, np.zeros((0, 100)))
    assert k0.shape == (0,) and b0.shape == (0,) and g0.shape == (0, 3, 3)


def test_fit_identical_vectors_clips_kappa() -> None:
    direction = np.array([0.3, -0.4, 0.5])
    fit = fit_kent_moments(np.tile(direction, (10, 1)))
    assert fit.kappa == KAPPA_MAX
    assert 0.0 <= fit.beta <= MAX_BETA_RATIO * fit.kappa
    assert _angle_deg(fit.mean, direction / np.linalg.norm(direction)) < 1e-6
    assert np.linalg.det(fit.gamma) == pytest.approx(1.0, abs=1e-12)
    single = fit_kent_moments([[0.0, 0.0, -2.0]])
    np.testing.assert_allclose(single.mean, [0.0, 0.0, -1.0], atol=1e-15)
    assert single.kappa == KAPPA_MAX


def test_fit_on_a_great_circle_clips_beta() -> None:
    # Directions spread along a narrow arc: r2 ~ 2 - 2 r1, beta / kappa -> 1/2.
    t = np.linspace(-1.2, 1.2, 201)
    x = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    fit = fit_kent_moments(x)
    assert fit.beta <= MAX_BETA_RATIO * fit.kappa
    assert _angle_deg(fit.major, np.array([0.0, 1.0, 0.0]), axial=True) < 1e-6
    assert np.isfinite(kent_log_normalizer(fit.kappa, fit.beta))


@pytest.mark.parametrize(
    ('x', 'weights', 'match'),
    [
        (np.ones((5, 2)), None, r'`x` to have shape \(N, 3\)'),
        (np.ones(3), None, r'`x` to have shape \(N, 3\)'),
        (np.zeros((0, 3)), None, r'N >= 1'),
        (np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), None, r'non-zero'),
        (np.array([[1.0, 0.0, np.nan]]), None, r'finite'),
        (np.eye(3), np.array([1.0, -1.0, 1.0]), r'`weights` to be non-negative'),
        (np.eye(3), np.zeros(3), r'`weights` to contain a positive value'),
        (np.eye(3), np.ones(4), r'`weights` to have shape \(3,\)'),
        (np.eye(3), np.array([1.0, np.inf, 1.0]), r'`weights` to be finite'),
    ],
)
def test_fit_rejects_bad_input(x: FloatArray, weights: FloatArray | None, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        fit_kent_moments(x, weights)


def test_batch_fit_rejects_bad_weights() -> None:
    x = np.eye(3)
    with pytest.raises(KentError, match=r'`weights` to have shape \(K, 3\)'):
        fit_kent_moments_batch(x, np.ones(3))
    with pytest.raises(KentError, match=r'`weights` to be non-negative'):
        fit_kent_moments_batch(x, -np.ones((2, 3)))
    with pytest.raises(KentError, match=r'`x` to have shape \(N, 3\)'):
        fit_kent_moments_batch(np.ones((3, 2)), np.ones((1, 3)))
