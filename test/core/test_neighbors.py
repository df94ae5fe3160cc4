"""NeighborIndex: both backends give the exact k nearest neighbours with cKDTree's conventions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from kentreg_ros.core import kernels
from kentreg_ros.core.scan.neighbors import HAVE_SMALL_GICP, NeighborIndex

NO_SMALL_GICP = 'small_gicp is not installed (pip install -e .[fast])'
NO_NUMBA = 'the kernels are not compiled (pip install -e .[fast])'
BACKENDS = [
    'scipy',
    pytest.param('compiled', marks=pytest.mark.skipif(not kernels.enabled(), reason=NO_NUMBA)),
    pytest.param(
        'small_gicp', marks=pytest.mark.skipif(not HAVE_SMALL_GICP, reason=NO_SMALL_GICP)
    ),
]


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize(('k', 'bound'), [(1, np.inf), (2, 0.05), (15, np.inf), (15, 0.08)])
def test_neighbours_equal_a_direct_kd_tree_query(backend: str, k: int, bound: float) -> None:
    rng = np.random.default_rng(k)
    points = rng.random((3000, 3))
    queries = rng.random((500, 3)) * 1.2 - 0.1  # some outside the cloud
    dist, idx = NeighborIndex(points, backend=backend).query(
        queries, k, distance_upper_bound=bound
    )
    ref_d, ref_i = cKDTree(points).query(queries, k=k, distance_upper_bound=bound)
    # Exact either way: equal distances (to rounding of the squared distances), equal indices
    # wherever no two neighbours are equidistant (random points: everywhere).
    np.testing.assert_allclose(dist, ref_d, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(idx, ref_i)


@pytest.mark.parametrize('backend', BACKENDS)
def test_more_neighbours_asked_than_points_are_padded_like_ckdtree(backend: str) -> None:
    points = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    dist, idx = NeighborIndex(points, backend=backend).query(np.zeros((1, 3)), 3)
    np.testing.assert_allclose(dist, [[0.0, 1.0, np.inf]])
    np.testing.assert_array_equal(idx, [[0, 1, 2]])


def test_unknown_backend_is_refused() -> None:
    with pytest.raises(ValueError, match='backend'):
        NeighborIndex(np.zeros((3, 3)), backend='faiss')


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize(('k', 'bound'), [(1, np.inf), (2, 0.05), (15, 0.08)])
def test_a_tree_built_in_another_order_answers_with_the_given_indices(
    backend: str, k: int, bound: float
) -> None:
    """The local map builds its tree on its points sorted by voxel key: the answers (found,
    not found, padded) are those of the tree on the points as given, pickled or not."""
    import pickle

    rng = np.random.default_rng(10 + k)
    points = rng.random((3000, 3))
    queries = rng.random((500, 3)) * 1.2 - 0.1
    order = np.argsort(np.floor(points / 0.1) @ [100.0, 10.0, 1.0], kind='stable')
    plain = NeighborIndex(points, backend=backend)
    ordered = NeighborIndex(points, backend=backend, order=order)
    want = plain.query(queries, k, distance_upper_bound=bound)
    for index in (ordered, pickle.loads(pickle.dumps(ordered))):
        got = index.query(queries, k, distance_upper_bound=bound)
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=1e-15)
        assert (got[1] == len(points)).any() == (bound < np.inf)  # some found none
        np.testing.assert_array_equal(
            index.neighbor_indices(points[:50], 15), plain.neighbor_indices(points[:50], 15)
        )
    with pytest.raises(ValueError, match='order'):
        NeighborIndex(points, order=order[:-1])


COMPILED = pytest.mark.skipif(not kernels.enabled(), reason=NO_NUMBA)


@COMPILED
@pytest.mark.parametrize(
    'cloud',
    ['identical', 'line', 'plane', 'orders_of_magnitude', 'duplicated'],
)
def test_the_compiled_tree_is_exact_on_degenerate_clouds(cloud: str) -> None:
    """Zero extents, one-dimensional clouds and coordinates over 30 orders of magnitude (where
    a midpoint split leaves one side nearly empty, so the tree falls back to the median):
    the distances are cKDTree's and the depth stays logarithmic."""
    rng = np.random.default_rng(3)
    n = 2000
    if cloud == 'identical':
        points = np.tile([1.0, 2.0, 3.0], (n, 1))
    elif cloud == 'line':
        points = np.outer(rng.random(n), [1.0, 2.0, -0.5])
    elif cloud == 'plane':
        points = np.column_stack([rng.random(n), rng.random(n), np.zeros(n)])
    elif cloud == 'orders_of_magnitude':
        points = np.outer(10.0 ** rng.uniform(-15, 15, n), [1.0, 1.0, 1.0])
    else:
        points = np.repeat(rng.random((n // 4, 3)), 4, axis=0)
    queries = np.concatenate([points[:200], rng.random((200, 3))])
    index = NeighborIndex(points, backend='compiled')
    dist, idx = index.query(queries, 5)
    ref_d, _ = cKDTree(points).query(queries, k=5)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-12, atol=0.0)
    # The indices hold points at those distances (ties may be broken either way).
    found = np.sqrt(((points[idx] - queries[:, None, :]) ** 2).sum(axis=2))
    np.testing.assert_allclose(found, dist, rtol=1e-12, atol=0.0)
    depth = kernels.kdtree_build(points)[-1]
    assert depth <= np.log(n) / np.log(16 / 15) + 1


@COMPILED
def test_the_compiled_tree_holds_more_nodes_than_half_full_leaves_need() -> None:
    """Clouds whose splits leave one point on a side (a node of 17-31 points may give its 1/16
    away): points doubling their distance along a line, and a trajectory that stands still and
    then walks (the viewpoints of a saved map, where this was found). The tree needs more
    nodes than leaves half full would; it grows its arrays for them (it once wrote past their
    end and crashed the process) and answers as cKDTree does."""
    rng = np.random.default_rng(5)
    clouds = [np.outer(2.0 ** np.arange(n), [1.0, 0.5, 0.25]) for n in (17, 24, 31, 47, 64)]
    still = rng.normal(scale=0.005, size=(23, 3))
    walk = np.outer(np.linspace(0.05, 9.0, 27), [0.4, 0.9, 0.05])
    clouds.append(np.concatenate([still, walk + rng.normal(scale=0.01, size=walk.shape)]))
    grew = 0
    for points in clouds:
        n = len(points)
        grew += len(kernels.kdtree_build(points)[2]) > 2 * (n // (kernels.KDTREE_LEAF // 2)) + 3
        queries = np.concatenate([points, rng.normal(scale=3.0, size=(300, 3))])
        dist, _ = NeighborIndex(points, backend='compiled').query(queries, 3)
        ref_d, _ = cKDTree(points).query(queries, k=3)
        np.testing.assert_allclose(dist, ref_d, rtol=1e-12, atol=0.0)
    assert grew >= 3


@COMPILED
@pytest.mark.skipif(not HAVE_SMALL_GICP, reason=NO_SMALL_GICP)
def test_the_compiled_tree_gives_small_gicps_distances_bit_for_bit() -> None:
    """The squared distances are summed in small_gicp's order, so a registration gets the same
    numbers whichever tree answers."""
    rng = np.random.default_rng(4)
    points = rng.normal(size=(5000, 3)) * [20.0, 20.0, 2.0]
    queries = points[:1000] + rng.normal(size=(1000, 3)) * 0.1
    got = NeighborIndex(points, backend='compiled').query(queries, 3)
    want = NeighborIndex(points, backend='small_gicp').query(queries, 3)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@COMPILED
def test_the_compiled_tree_of_no_points_finds_nothing() -> None:
    dist, idx = NeighborIndex(np.zeros((0, 3)), backend='compiled').query(np.ones((2, 3)), 2)
    assert np.isinf(dist).all()
    np.testing.assert_array_equal(idx, [[0, 0], [0, 0]])


def test_the_compiled_backend_is_refused_without_the_kernels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(kernels.DISABLE_ENV, '1')
    with pytest.raises(ValueError, match='compiled'):
        NeighborIndex(np.zeros((3, 3)), backend='compiled')
    assert NeighborIndex(np.zeros((3, 3))).backend in ('small_gicp', 'scipy')


@COMPILED
def test_the_trees_median_selection_puts_each_row_where_a_sort_would() -> None:
    """A lopsided node is split at its median by selection, not by a sort: the row at the
    split holds the coordinate a sort would put there, none before it is larger, none after it
    smaller, the rows travel whole with their indices and nothing outside the node moves."""
    from kentreg_ros.core.kernels import _jit_tree

    rng = np.random.default_rng(6)
    for trial in range(200):
        n = int(rng.integers(1, 60))
        # Few distinct values: ties everywhere, as on a plane or a wall.
        rows = rng.integers(0, 4 if trial % 2 else 50, size=(n, 3)).astype(np.float64)
        s = int(rng.integers(0, n))
        e = int(rng.integers(s + 1, n + 1))
        k = int(rng.integers(s, e))
        d = int(rng.integers(0, 3))
        tp, perm = rows.copy(), np.arange(n)
        _jit_tree._select(tp, perm, s, e, k, d)
        assert tp[k, d] == np.sort(rows[s:e, d])[k - s]
        assert (tp[s:k, d] <= tp[k, d]).all() and (tp[k + 1 : e, d] >= tp[k, d]).all()
        np.testing.assert_array_equal(tp, rows[perm])
        np.testing.assert_array_equal(perm[:s], np.arange(s))
        np.testing.assert_array_equal(perm[e:], np.arange(e, n))
