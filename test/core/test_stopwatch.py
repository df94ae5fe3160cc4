"""The stopwatch that carries stage timings."""

from __future__ import annotations

import pytest

from kentreg_ros.core.stopwatch import Stopwatch


def test_a_stage_timed_twice_reports_the_sum_and_merge_prefixes() -> None:
    watch = Stopwatch()
    watch.add('refine', 1.5)
    with watch('refine'):
        pass
    assert watch['refine'] >= 1.5 and 'refine' in watch and 'rotation' not in watch
    other = Stopwatch()
    other.add('normals', 2.0)
    watch.merge(other.as_dict(), prefix='prepare.')
    assert watch.as_dict()['prepare.normals'] == 2.0


def test_a_stage_that_raises_is_still_timed() -> None:
    watch = Stopwatch()
    with pytest.raises(ValueError), watch('search'):
        raise ValueError('boom')
    assert watch['search'] >= 0.0
