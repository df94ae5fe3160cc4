"""Normal-space sampling of the position stages and the voxel keys' radix argsort."""

from __future__ import annotations

import numpy as np
import pytest

from kentreg_ros.core.scan.sampling import stratified_sample
from kentreg_ros.core.scan.voxels import argsort_keys


@pytest.mark.parametrize('seed', range(5))
def test_stratified_sample_keeps_min_of_size_and_cap_evenly_spaced(seed: int) -> None:
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 6, size=int(rng.integers(1, 3000)))
    cap = int(rng.integers(1, 400))
    idx = stratified_sample(labels, cap)
    assert np.all(np.diff(idx) > 0)
    for k in np.unique(labels):
        members = np.flatnonzero(labels == k)
        kept = min(len(members), cap)
        expected = members[(np.arange(kept) * len(members)) // kept]
        np.testing.assert_array_equal(idx[labels[idx] == k], expected)


def test_stratified_sample_keeps_small_clusters_whole_and_thins_large_ones() -> None:
    labels = np.repeat([0, 1, 2], [50, 5000, 900])
    idx = stratified_sample(labels, 1000)
    counts = np.bincount(labels[idx])
    assert counts.tolist() == [50, 1000, 900]
    # evenly spaced in storage order: gaps within the thinned cluster are 5 points
    assert set(np.diff(idx[labels[idx] == 1]).tolist()) == {5}
    np.testing.assert_array_equal(stratified_sample(labels, 0), np.arange(len(labels)))
    np.testing.assert_array_equal(stratified_sample(labels, 5000), np.arange(len(labels)))


@pytest.mark.parametrize('jit', ['', '1'])
@pytest.mark.parametrize('high', [1, 7, 2**16, 2**20, 2**40, 2**62])
def test_argsort_keys_is_the_stable_argsort(
    high: int, jit: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv('KENTREG_NO_JIT', jit)  # compiled (where numba is installed), numpy
    rng = np.random.default_rng(high % 97)
    for n in (0, 1, 13, 5000):
        keys = rng.integers(0, high, size=n, dtype=np.int64)
        # Duplicates: stability decides the order among equal keys.
        keys = np.concatenate([keys, keys[: n // 3]])
        np.testing.assert_array_equal(argsort_keys(keys), np.argsort(keys, kind='stable'))
    negative = np.array([3, -1, 3, -7, 0], dtype=np.int64)
    np.testing.assert_array_equal(argsort_keys(negative), np.argsort(negative, kind='stable'))
