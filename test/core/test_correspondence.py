"""Exact nearest-neighbour correspondences with re-querying only where they may have changed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from kentreg_ros.core import exp_so3
from kentreg_ros.core.registration.correspondence import NearestNeighborCache


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    target = rng.uniform(-5.0, 5.0, size=(4000, 3)) * [1.0, 1.0, 0.2]
    source = target[rng.choice(len(target), 2500)] + rng.normal(scale=0.05, size=(2500, 3))
    return source, target


def test_cache_returns_exactly_the_fresh_query_while_points_move_and_the_gate_shrinks() -> None:
    rng = np.random.default_rng(0)
    source, target = _scene(rng)
    tree = cKDTree(target)
    cache = NearestNeighborCache(tree, target, len(source))
    R, t, gate = np.eye(3), np.zeros(3), 1.0
    for it in range(25):
        x = source @ R.T + t
        d_ref, i_ref = tree.query(x, k=1, distance_upper_bound=gate)
        d, i = cache.query(x, gate)
        np.testing.assert_array_equal(i, i_ref)
        np.testing.assert_array_equal(np.isfinite(d), np.isfinite(d_ref))
        np.testing.assert_allclose(d[np.isfinite(d)], d_ref[np.isfinite(d_ref)], rtol=1e-12)
        step = 0.5 * 0.6**it  # large moves first, then millimetres, as in the refinement
        R = exp_so3(rng.normal(size=3) * 0.05 * step) @ R
        t = t + rng.normal(size=3) * 0.2 * step
        gate = max(0.7 * gate, 0.2)
    assert cache.n_calls == 25


def test_cache_skips_the_query_for_points_that_barely_moved() -> None:
    rng = np.random.default_rng(1)
    source, target = _scene(rng)
    cache = NearestNeighborCache(cKDTree(target), target, len(source))
    cache.query(source, 0.5)
    assert cache.n_queried == len(source)
    cache.query(source + [1e-4, 0.0, 0.0], 0.5)
    # A 0.1 mm move is below nearly every point's certified radius.
    assert cache.n_queried < 1.05 * len(source)


def test_cache_certifies_a_swap_between_two_close_target_points_without_a_query() -> None:
    # A query point between two target points (1 m apart; the third is 9.5 m away) crosses the
    # midpoint: its nearest neighbour changes, and the two cached candidates prove which.
    target = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    cache = NearestNeighborCache(cKDTree(target), target, 1)
    for x, expected in ((0.49, 0), (0.51, 1), (0.45, 0), (0.9, 1)):
        d, i = cache.query(np.array([[x, 0.0, 0.0]]), 5.0)
        assert i[0] == expected
        assert d[0] == pytest.approx(min(x, 1.0 - x))
    assert cache.n_queried == 1
    # Beyond what the third neighbour's distance certifies, it queries again.
    d, i = cache.query(np.array([[6.0, 0.0, 0.0]]), 5.0)
    assert (i[0], d[0]) == (2, pytest.approx(4.0))
    assert cache.n_queried == 2


def test_cache_rejects_a_target_that_is_not_the_trees() -> None:
    target = np.random.default_rng(2).random((50, 3))
    with pytest.raises(ValueError, match='`target` to hold the 50 points'):
        NearestNeighborCache(cKDTree(target), target[:10], 5)
