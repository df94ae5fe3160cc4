"""End-to-end tests of register(): synthetic scenes with known motion, the real pair, bad input."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import pytest
from scenes import (
    SMALL_GICP_PAIR,
    add_outliers,
    box_room,
    corridor,
    pose_errors,
    random_transform,
    read_ply_xyz,
    transform_points,
)

from kentreg_ros.core import (
    InvalidPointCloudError,
    KentRegConfig,
    RegistrationResult,
    Status,
    exp_so3,
    make_transform,
    prepare_scan,
    register,
)
from kentreg_ros.core.config import Mode
from kentreg_ros.core.registration.result import PoseEvidence, finish_result
from kentreg_ros.core.scan import prepared as scan_module

needs_pair = pytest.mark.skipif(
    not SMALL_GICP_PAIR.exists(),
    reason=f'real data not present at {SMALL_GICP_PAIR} (../shared exists only in CI/dev)',
)


def _room_pair(
    seed: int, angle: float, dist: float, outliers: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    target = box_room(rng, 10000)
    T = random_transform(rng, angle, dist)  # T_target_source
    source = transform_points(np.linalg.inv(T), box_room(np.random.default_rng(seed), 10000))
    source = source + rng.normal(scale=0.005, size=source.shape)
    return add_outliers(rng, source, outliers), add_outliers(rng, target, outliers), T


@pytest.mark.parametrize(
    ('seed', 'angle', 'dist', 'outliers'),
    [(0, 10.0, 0.3, 0.0), (1, 20.0, 0.5, 0.0), (2, 10.0, 0.3, 0.3)],
)
def test_robust_recovers_known_motion_in_synthetic_room(
    seed: int, angle: float, dist: float, outliers: float
) -> None:
    """From no start. The box room is nearly symmetric (its twins turned 90-180 deg fit within
    a tenth once 30 % outliers blur the fit): then the result must say ``ambiguous`` and list
    the twins, while the best fit is still the right pose."""
    source, target, T = _room_pair(seed, angle, dist, outliers)
    result = register(source, target, viewpoint=(0.0, 0.0, 0.2))
    e_r, e_t = pose_errors(result.T_target_source, T)
    assert result.status in ('converged', 'max_iterations', 'ambiguous'), result.message
    assert (result.status == 'ambiguous') == result.ambiguous
    assert not result.ambiguous or len(result.alternatives) > 0
    assert e_r < 0.2 and e_t < 0.02, (e_r, e_t)


def test_result_has_the_documented_fields() -> None:
    source, target, T = _room_pair(3, 5.0, 0.2)
    result = register(source, target)
    assert isinstance(result, RegistrationResult)
    assert result.T_target_source.shape == (4, 4)
    assert result.covariance.shape == (6, 6)
    assert np.all(np.linalg.eigvalsh(result.covariance) >= 0)
    assert result.kappa.shape == result.beta.shape and len(result.kappa) >= 1
    assert np.all(result.beta < result.kappa / 2)
    assert len(result.log_likelihood) >= 1 and result.iterations > 0
    assert 0.0 < result.inlier_fraction <= 1.0
    assert {'rotation', 'translation', 'refine', 'total'} <= set(result.timings)
    assert set(result.stages) >= {'rotation', 'translation', 'refine'}
    assert isinstance(result.status, Status) and result.mode is Mode.ROBUST


def test_timings_name_each_stage_once_summed_over_candidates() -> None:
    """One stopwatch per registration: every stage reports its total (over the candidate
    poses of a search too), the preparation of each cloud included, within the total."""
    source, target, _ = _room_pair(3, 5.0, 0.2)
    s, t = prepare_scan(source), prepare_scan(target)
    stages = ['prepare_source', 'prepare_target', 'rotation', 'translation', 'refine']
    stages += ['fit', 'covariance']
    local = register(s, t, init=np.eye(4))
    assert list(local.timings) == [*stages, 'total']
    searched = register(s, t, global_search=True)
    assert searched.hypotheses > 0
    assert set(searched.timings) == {*stages, 'search', 'vouch', 'total'}  # no start: vouched
    for result in (local, searched):
        assert all(ms >= 0.0 for ms in result.timings.values())
        parts = sum(ms for stage, ms in result.timings.items() if stage != 'total')
        assert parts <= result.timings['total'] + 1e-6
    assert set(s.timings) == {
        'downsample', 'neighbours', 'normals', 'outliers', 'clustering', 'total'
    }  # fmt: skip
    paper = register(s, t, init=np.eye(4), config=KentRegConfig.paper())
    assert list(paper.timings) == [*stages[:5], 'total'] and paper.timings['refine'] == 0.0


def _evidence(**changes: Any) -> PoseEvidence:
    values: dict[str, Any] = {
        'T_target_source': make_transform(exp_so3(np.array([0.0, 0.0, 0.1])), np.ones(3)),
        'converged': True,
        'iterations': 7,
        'kappa': np.array([50.0]),
        'beta': np.array([5.0]),
        'log_likelihood': (1.0, 2.0),
        'inlier_fraction': 0.8,
        'covariance': np.eye(6),
        'degenerate_directions': np.zeros((0, 3)),
        'rotation_degenerate': False,
        'stages': {},
    }
    return PoseEvidence(**(values | changes))


@pytest.mark.parametrize(
    ('changes', 'status', 'message'),
    [
        ({}, Status.CONVERGED, 'Converged.'),
        ({'converged': False}, Status.MAX_ITERATIONS, 'iteration limit'),
        ({'degenerate_directions': np.array([[1.0, 0.0, 0.0]])}, Status.DEGENERATE, 'along'),
        ({'rotation_degenerate': True}, Status.DEGENERATE, 'rotation about one axis'),
        ({'inlier_fraction': 0.01}, Status.FAILED, r'Only 1.0% of the source points'),
        ({'T_target_source': np.full((4, 4), np.inf)}, Status.FAILED, 'not finite'),
    ],
)
def test_finish_result_judges_the_evidence_into_a_status(
    changes: dict, status: Status, message: str
) -> None:
    result = finish_result(
        _evidence(**changes), mode=Mode.ROBUST, n_source=10, n_target=12, timings={'total': 1.0}
    )
    assert result.status is status and result.status == status.value
    assert re.search(message, result.message), result.message
    assert result.ok == (status != Status.FAILED)
    assert result.converged == (status != Status.FAILED and changes.get('converged', True))
    assert result.degenerate == (status == Status.DEGENERATE)
    assert (result.n_source, result.n_target, result.timings) == (10, 12, {'total': 1.0})
    if status == Status.FAILED and 'T_target_source' in changes:
        assert np.isnan(result.T_target_source).all()  # never a silent identity


def test_prepared_scans_are_reusable_and_give_the_same_result(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    source, target, _ = _room_pair(4, 8.0, 0.2)
    cfg = KentRegConfig()
    prepared: list[object] = []  # what register() prepares itself (counted, not timed)
    monkeypatch.setattr(
        scan_module, 'prepare_scan', lambda p, **kw: prepared.append(p) or prepare_scan(p, **kw)
    )
    direct = register(source, target, config=cfg)
    assert len(prepared) == 2
    s, t = prepare_scan(source, config=cfg), prepare_scan(target, config=cfg)
    cached = register(s, t, config=cfg)
    np.testing.assert_allclose(cached.T_target_source, direct.T_target_source, atol=1e-9)
    assert len(prepared) == 2  # nothing recomputed


def test_precomputed_normals_are_used() -> None:
    source, target, T = _room_pair(5, 5.0, 0.1)
    cfg = KentRegConfig()
    s, t = prepare_scan(source, config=cfg), prepare_scan(target, config=cfg)
    result = register(s.points, t.points, source_normals=s.normals, target_normals=t.normals)
    e_r, e_t = pose_errors(result.T_target_source, T)
    assert e_r < 0.2 and e_t < 0.02


def _paper_recipe_checks(result: RegistrationResult, source: Any, target: Any) -> None:
    """What Algorithms 1-2 of the paper must return, whatever its accuracy on the scene."""
    assert result.mode == 'paper'
    assert result.status != 'failed', result.message
    # Per-cluster EM then rotation averaging: a proper rotation, one Kent fit per cluster pair.
    R = result.T_target_source[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert len(result.kappa) == KentRegConfig().clustering.n_clusters
    assert np.all(result.kappa > 0) and np.all(result.beta < result.kappa / 2)  # Kent: 2b < k
    # t = mu_y - R mu_x from the centroids of the clouds it registered, and nothing after it.
    t = result.T_target_source[:3, 3]
    expected = target.points.mean(axis=0) - R @ source.points.mean(axis=0)
    np.testing.assert_allclose(t, expected, atol=1e-9)
    assert result.stages.keys() == {'rotation', 'translation'}
    np.testing.assert_array_equal(result.stages['translation'], result.T_target_source)
    np.testing.assert_array_equal(result.stages['rotation'][:3, :3], R)


def test_paper_mode_follows_the_papers_recipe_on_a_synthetic_room() -> None:
    """From identity, with a known 5 deg / 0 m motion: the recipe as written (its accuracy
    depends on the k-means partition, see README, so it is not what is checked here)."""
    source, target, _ = _room_pair(6, 5.0, 0.0)
    cfg = KentRegConfig.paper()
    s, t = prepare_scan(source, config=cfg), prepare_scan(target, config=cfg)
    result = register(s, t, init=np.eye(4), config=cfg)
    _paper_recipe_checks(result, s, t)


#: Each switch of the robust pipeline, its ablated value, and the first stage it acts on.
ABLATIONS = [
    ('em.kent_beta', True, 'rotation'),
    ('em.rotation', 'averaged', 'rotation'),
    ('translation.method', 'centroid', 'translation'),
    ('translation.cross_correlation', False, 'translation'),
    ('translation.max_iterations', 20, 'translation'),
    ('refine.method', 'plane_to_plane', 'refine'),
    ('refine.method', 'none', 'refine'),
    ('refine.normal_weight', False, 'refine'),
    ('refine.max_step_scale', 1.0, 'refine'),
]
STAGE_ORDER = ('rotation', 'translation', 'refine')


@pytest.fixture(scope='module')
def ablation_room() -> tuple[object, object, np.ndarray, RegistrationResult]:
    """A synthetic room pair (5 deg, 0.1 m), prepared once (the ablations do not touch the
    preparation), and the default pipeline's result from identity."""
    source, target, T = _room_pair(7, 5.0, 0.1)
    cfg = KentRegConfig()
    s, t = prepare_scan(source, config=cfg), prepare_scan(target, config=cfg)
    return s, t, T, register(s, t, init=np.eye(4), config=cfg)


@pytest.mark.parametrize(('key', 'value', 'stage'), ABLATIONS, ids=lambda v: str(v))
def test_every_ablation_switch_reaches_its_stage_and_still_registers(
    ablation_room: tuple, key: str, value: object, stage: str
) -> None:
    """Each ablation must really change the configuration and reach the stage it switches
    (everything before that stage is bit-identical to the default run from the same start,
    that stage differs), and, being a variant of the robust pipeline on a clean room in its
    basin, must stay within the paper's failure thresholds (2 deg, 0.2 m)."""
    s, t, T, default = ablation_room
    default_cfg = KentRegConfig()
    cfg = default_cfg.with_updates({key: value})
    assert cfg.to_flat_dict()[key] == value != default_cfg.to_flat_dict()[key]
    result = register(s, t, init=np.eye(4), config=cfg)
    assert result.status != 'failed', result.message
    e_r, e_t = pose_errors(result.T_target_source, T)
    assert e_r < 2.0 and e_t < 0.2, (key, value, e_r, e_t)
    before = STAGE_ORDER[: STAGE_ORDER.index(stage)]
    for earlier in before:
        np.testing.assert_array_equal(result.stages[earlier], default.stages[earlier])
    if (key, value) == ('refine.method', 'none'):
        assert 'refine' not in result.stages
        np.testing.assert_array_equal(result.T_target_source, result.stages['translation'])
    else:
        assert not np.array_equal(result.stages[stage], default.stages[stage]), key
    if key == 'translation.method' or key == 'translation.cross_correlation':
        assert 'cross_correlation' not in result.stages  # the plane-offset start was skipped
    if (key, value) == ('translation.method', 'centroid'):
        R = result.stages['translation'][:3, :3]
        expected = t.points.mean(axis=0) - R @ s.points.mean(axis=0)
        np.testing.assert_allclose(result.stages['translation'][:3, 3], expected, atol=1e-9)


def test_corridor_flags_degenerate_translation_axis() -> None:
    rng = np.random.default_rng(8)
    target = corridor(rng)
    source = corridor(rng)  # same corridor, new samples: along-axis motion unobservable
    result = register(source, target)
    assert result.degenerate
    assert result.status == 'degenerate'
    assert 'poorly constrained' in result.message
    axis = np.abs(result.degenerate_directions[0])
    assert axis[0] > 0.95, result.degenerate_directions


def test_single_plane_is_degenerate_not_silent() -> None:
    rng = np.random.default_rng(9)
    plane = np.column_stack(
        [rng.uniform(-5, 5, 3000), rng.uniform(-5, 5, 3000), rng.normal(scale=0.005, size=3000)]
    )
    result = register(plane + [0.1, 0.0, 0.0], plane)
    assert result.status == 'degenerate' and result.degenerate


def test_identical_clouds_give_identity_and_converge() -> None:
    source, _, _ = _room_pair(10, 0.0, 0.0)
    result = register(source, source)
    e_r, e_t = pose_errors(result.T_target_source, np.eye(4))
    assert result.converged and e_r < 1e-3 and e_t < 1e-4


@pytest.mark.parametrize(
    ('points', 'match'),
    [
        (np.zeros((100, 2)), r'shape \(N, 3\)'),
        (np.full((100, 3), np.nan), 'NaN or inf'),
        (np.array([[0, 0, 0], [np.inf, 1, 1]] * 50, dtype=float), 'NaN or inf'),
        (np.random.default_rng(0).random((10, 3)), 'at least'),
        (np.zeros((0, 3)), 'at least'),
    ],
)
def test_register_rejects_bad_clouds(points: np.ndarray, match: str) -> None:
    good, _, _ = _room_pair(11, 0.0, 0.0)
    with pytest.raises(InvalidPointCloudError, match=match):
        register(points, good)
    with pytest.raises(InvalidPointCloudError, match=match):
        register(good, points)


def test_register_rejects_bad_init() -> None:
    good, _, _ = _room_pair(12, 0.0, 0.0)
    with pytest.raises(ValueError, match='init'):
        register(good, good, init=np.eye(3))
    with pytest.raises(ValueError, match='rotation'):
        register(good, good, init=np.diag([1.0, 1.0, -1.0, 1.0]))


@pytest.fixture(scope='module')
def real_pair() -> tuple[object, object, np.ndarray]:
    cfg = KentRegConfig()
    source = read_ply_xyz(SMALL_GICP_PAIR / 'source.ply')
    target = read_ply_xyz(SMALL_GICP_PAIR / 'target.ply')
    T_ref = np.loadtxt(SMALL_GICP_PAIR / 'T_target_source.txt')
    return prepare_scan(source, config=cfg), prepare_scan(target, config=cfg), T_ref


@needs_pair
@pytest.mark.parametrize('start', ['identity', 'perturbed'])
def test_robust_mode_on_real_small_gicp_pair(real_pair: tuple, start: str) -> None:
    """Within 0.3 deg / 3 cm of the stored transform (itself good to ~0.2 deg / 2 cm)."""
    source, target, T_ref = real_pair
    init = np.eye(4)
    if start == 'perturbed':
        rng = np.random.default_rng(1)
        axis = rng.normal(size=3)
        direction = rng.normal(size=3)
        P = make_transform(
            exp_so3(axis / np.linalg.norm(axis) * np.radians(10.0)),
            direction / np.linalg.norm(direction) * 0.5,
        )
        init = T_ref @ P
        assert pose_errors(init, T_ref)[0] > 9.9
    result = register(source, target, init=init)
    e_r, e_t = pose_errors(result.T_target_source, T_ref)
    assert e_r < 0.3 and e_t < 0.03, (e_r, e_t)


@needs_pair
@pytest.mark.parametrize('seed', [5, 6])
def test_real_pair_accuracy_holds_under_micrometre_perturbations(seed: int) -> None:
    """The bounds of the test above must not hinge on rounding: 1 um of noise on the raw scans.

    Measured before the refinement followed its creep to the fixed point (tolerance 5e-4,
    no step lengthening): 0.246 deg / 22 mm on the exact data but about 0.27 deg / 31 mm with
    such noise in 5 of 6 seeds tried (seed 5 here among them): where the iteration stopped
    along a slow creep decided the outcome. Now 0.245-0.267 deg / 16-22 mm over the exact data
    and 4 noise seeds.
    """
    rng = np.random.default_rng(seed)
    cfg = KentRegConfig()
    scans = []
    for name in ('source', 'target'):
        raw = read_ply_xyz(SMALL_GICP_PAIR / f'{name}.ply')
        scans.append(prepare_scan(raw + rng.normal(scale=1e-6, size=raw.shape), config=cfg))
    T_ref = np.loadtxt(SMALL_GICP_PAIR / 'T_target_source.txt')
    result = register(scans[0], scans[1], config=cfg)
    assert result.status == 'converged', result.message
    e_r, e_t = pose_errors(result.T_target_source, T_ref)
    assert e_r < 0.3 and e_t < 0.03, (e_r, e_t)


@needs_pair
def test_paper_mode_follows_the_papers_recipe_on_the_real_pair(real_pair: tuple) -> None:
    """The paper's recipe as written on real scans from another viewpoint. Its translation is
    the centroid difference, which is why it leaves most of the true 0.5 m motion uncorrected
    there (README: 0.54 m): the two scans see different parts of the scene."""
    source, target, _ = real_pair
    result = register(source, target, config=KentRegConfig.paper())
    _paper_recipe_checks(result, source, target)
