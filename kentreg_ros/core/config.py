"""The research configuration of the registrar and the odometry: one frozen dataclass tree.

:class:`KentRegConfig` is the single source of defaults, ranges and validation of everything the
method can be told, the paper's recipe and every ablation included (dotted names such as
``em.max_iterations``). Python, the benchmarks and the command lines' ``--set`` reach all of it;
the operator's product parameters (:mod:`kentreg_ros.io.params`) are a few of its fields under
flat names, and the node declares only those.

Every field carries metadata: a one-line ``description`` and either a numeric ``range``
(inclusive) or a tuple of ``choices`` (:func:`~kentreg_ros.core.fields.setting`);
:func:`~kentreg_ros.core.fields.iter_fields` walks the tree with it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, is_dataclass, replace
from enum import StrEnum
from typing import Any, get_type_hints

from kentreg_ros.core.errors import ConfigError
from kentreg_ros.core.fields import (
    Section,
    flatten_keys,
    iter_fields,
    nest_keys,
    plain_value,
    setting,
)
from kentreg_ros.core.localization_config import LocalizationConfig
from kentreg_ros.core.odometry_config import OdometryConfig


class Mode(StrEnum):
    """Which registration runs: the improved pipeline or the paper's recipe as written."""

    ROBUST = 'robust'
    PAPER = 'paper'


class EMRotation(StrEnum):
    """The EM's M-step: one rotation for all clusters, or per-cluster EM then averaging."""

    SHARED = 'shared'
    AVERAGED = 'averaged'


class TranslationMethod(StrEnum):
    """Translation with the rotation fixed: robust point-to-plane, or the paper's centroids."""

    POINT_TO_PLANE = 'point_to_plane'
    CENTROID = 'centroid'


class RefineMethod(StrEnum):
    """Cost of the joint 6-DOF refinement."""

    PLANE_TO_PLANE = 'plane_to_plane'
    POINT_TO_PLANE = 'point_to_plane'
    NONE = 'none'


class SearchMode(StrEnum):
    """When :func:`~kentreg_ros.core.registration.register` searches SO(3) without a start."""

    AUTO = 'auto'
    ALWAYS = 'always'
    NEVER = 'never'


@dataclass(frozen=True)
class PreprocessConfig(Section, prefix='preprocess.'):
    """Range cropping and voxel downsampling applied to every scan."""

    voxel_size: float = setting(
        0.0,
        'Voxel edge in metres for downsampling; 0 picks it per scan to reach target_points.',
        range=(0.0, 10.0),
    )
    target_points: int = setting(
        10000,
        'Voxels kept by automatic voxel downsampling (paper: ~10,000 points). Only voxels '
        'holding at least min_voxel_points returns count, so stray returns cannot choose the '
        'size.',
        range=(100, 2_000_000),
    )
    min_voxel_points: int = setting(
        2,
        'Returns a voxel must hold to be kept. A voxel with a single return is where isolated '
        'returns (dust, rain, multipath) land and says nothing about a surface; the floor is '
        'raised automatically while uniform stray returns at the observed rate of single-return '
        'voxels would fill more than 5 % of the kept voxels. 1 keeps every voxel.',
        range=(1, 8),
    )
    min_range: float = setting(
        0.0, 'Drop points closer to the sensor than this (m).', range=(0.0, 1000.0)
    )
    max_range: float = setting(
        0.0, 'Drop points farther than this (m); 0 keeps all.', range=(0.0, 10000.0)
    )

    def check(self) -> None:
        if self.max_range > 0.0 and self.min_range >= self.max_range:
            raise ConfigError(
                f'Expected preprocess.min_range < preprocess.max_range (or max_range 0: no '
                f'limit), got min_range={self.min_range} >= max_range={self.max_range}: every '
                'point would be cropped.'
            )


@dataclass(frozen=True)
class NormalsConfig(Section, prefix='normals.'):
    """PCA surface normals and their cosine-similarity outlier removal."""

    k_neighbors: int = setting(15, 'Neighbours for PCA normals (paper: 15).', range=(5, 100))
    max_flatness: float = setting(
        0.5,
        'Keep a normal only where its neighbourhood is a surface: smallest over middle '
        'eigenvalue of the neighbourhood covariance at most this. At 0.5 the normal of 15 '
        'neighbours is determined to about 10 deg, which keeps rough surfaces (grass, bark, '
        'gravel: on a sparse or narrow-view scan the only ones holding some directions); '
        'above it the points form a line or a blob (far scan rings, stray returns), whose '
        'normal is arbitrary. 1 keeps every normal.',
        range=(0.0, 1.0),
    )
    outlier_cosine: float = setting(
        0.8,
        'Remove a normal whose cosine to its neighbourhood mean normal is below this; '
        '-1 disables.',
        range=(-1.0, 1.0),
    )


@dataclass(frozen=True)
class ClusteringConfig(Section, prefix='clustering.'):
    """Spherical k-means over the normals."""

    n_clusters: int = setting(6, 'Number of spherical k-means clusters K.', range=(1, 64))
    max_iterations: int = setting(50, 'Spherical k-means iterations.', range=(1, 1000))
    seed: int = setting(0, 'Seed of the k-means++ initialisation.', range=(0, 2**31 - 1))
    restarts: int = setting(3, 'k-means++ restarts; the best clustering is kept.', range=(1, 100))
    restart_sample: int = setting(
        2000,
        'The restarts run on a seeded subset of this many normals and only the best is '
        'continued on all of them (0: every restart on all normals): a few thousand normals '
        'already show where the clusters lie, and the continuation settles their borders.',
        range=(0, 10_000_000),
    )


@dataclass(frozen=True)
class EMConfig(Section, prefix='em.'):
    """The EM on the sphere that estimates rotation from normals."""

    max_iterations: int = setting(50, 'Maximum EM iterations.', range=(1, 10000))
    tolerance: float = setting(
        1e-4,
        'Stop when the relative change of Q or the rotation change (rad) is below this.',
        range=(0.0, 1.0),
    )
    outlier_weight: float = setting(
        0.1, 'Mixture weight pi0 of the uniform outlier component.', range=(0.0, 0.99)
    )
    kent_beta: bool = setting(
        False,
        'Robust mode: put the Kent ovalness beta into the E-step kernels as the paper does. '
        "The paper's beta term acts on the observed normal itself (a cluster-wide pull toward "
        "the cluster's major axis), which biased the rotation where a cluster's spread differs "
        'between views; beta is estimated and reported either way (paper mode always uses it).',
    )
    rotation: EMRotation = setting(
        EMRotation.SHARED,
        'Robust mode: one rotation shared by all clusters, or per-cluster EM then averaging.',
    )
    kappa_cap_start: float = setting(
        20.0,
        "Robust mode: cap on the kernels' kappa in the first pass, rising each pass: 20 is an "
        'angular spread of ~13 deg, a basin as wide as a cluster of normals.',
        range=(1.0, 1e6),
    )
    kappa_cap_end: float = setting(
        2000.0,
        'Robust mode: final cap on kappa: ~1.3 deg, finer than the noise of PCA normals, so it '
        'only stops a perfectly flat synthetic cluster from collapsing the kernel.',
        range=(1.0, 1e7),
    )
    kappa_cap_growth: float = setting(
        2.0,
        'Robust mode: factor by which the kappa cap rises per pass (the kernel narrows by '
        'sqrt(2) per pass: the rotation follows it from one basin into the next).',
        range=(1.0, 100.0),
    )
    max_points_per_cluster: int = setting(
        1500,
        'Paper mode: normals per cluster and cloud used in the dense M x N posterior matrix '
        '(a seeded subsample bounds memory and time).',
        range=(10, 100000),
    )

    def check(self) -> None:
        if self.kappa_cap_end < self.kappa_cap_start:
            raise ConfigError(
                f'Expected em.kappa_cap_end >= em.kappa_cap_start, got '
                f'{self.kappa_cap_end} < {self.kappa_cap_start}.'
            )


@dataclass(frozen=True)
class TranslationConfig(Section, prefix='translation.'):
    """Translation with the rotation fixed."""

    method: TranslationMethod = setting(
        TranslationMethod.POINT_TO_PLANE,
        "Robust mode: 'point_to_plane' (robust 3-DOF least squares) or 'centroid' (paper).",
    )
    cross_correlation: bool = setting(
        True, 'Start from a per-direction cross-correlation of plane offsets.'
    )
    max_iterations: int = setting(
        3,
        'Iterations of the 3-DOF solve. The joint refinement re-solves all 6 DOF, so this '
        'stage only places it in its basin; 3 lets the gate shrink from its start to near its '
        'floor.',
        range=(1, 1000),
    )
    tolerance: float = setting(
        1e-3, 'Stop when the translation update is below this (m).', range=(0.0, 1.0)
    )
    max_correspondence_distance: float = setting(
        1.0,
        'Largest point-to-point distance accepted as a correspondence (m).',
        range=(0.001, 100.0),
    )
    max_shift: float = setting(
        2.0,
        'How far (m) the translation may lie from its start along each plane normal in the '
        'cross-correlation: 2 m is 20 m/s at 10 Hz, beyond the motion between scans of any '
        'platform the odometry is meant for.',
        range=(0.0, 1000.0),
    )
    degeneracy_ratio: float = setting(
        0.02,
        'Flag degeneracy along a direction whose eigenvalue of the normal matrix (of the '
        'translation, or of the rotation EM) is below this share of the largest. In robust '
        'mode a translation direction found so is flagged only when the pose moved along it '
        'by the distinct-pose gate (4 sampling spacings) still fits at least '
        'search.ambiguity_ratio as well: sparse, narrow views hold a direction with a few '
        'dozen points and a small eigenvalue, which the fit tells apart from a corridor, '
        'where the points slide along the walls.',
        range=(0.0, 1.0),
    )


@dataclass(frozen=True)
class RefineConfig(Section, prefix='refine.'):
    """Final joint 6-DOF refinement on positions and Kent-weighted normals."""

    method: RefineMethod = setting(
        RefineMethod.POINT_TO_PLANE,
        "Joint refinement cost: 'point_to_plane', 'plane_to_plane' (GICP-like), or 'none'.",
    )
    normal_weight: bool = setting(
        True, 'Weight correspondences by the Kent likelihood of their normals (hybrid).'
    )
    max_iterations: int = setting(
        50,
        'Gauss-Newton iterations at most: enough to follow a creep along a weakly constrained '
        'direction to the tolerance (see max_step_scale).',
        range=(1, 1000),
    )
    max_correspondence_distance: float = setting(
        1.0,
        'Largest point-to-point distance accepted as a correspondence (m).',
        range=(0.001, 100.0),
    )
    tolerance: float = setting(
        5e-5,
        'Stop when the update is below this (rad and m): far below the sensor noise, so that a '
        'creep of nearest-neighbour Gauss-Newton along a weakly constrained direction is '
        'followed to its fixed point (see max_step_scale) and the result does not depend on '
        'where it stopped.',
        range=(0.0, 1.0),
    )
    max_cluster_points: int = setting(
        1000,
        'Source points per normal cluster used by the translation, the refinement and the fit '
        '(0: all): normal-space sampling with the Kent clusters as strata, evenly in space. '
        'Small clusters, which hold the weakly constrained directions, keep every point; large '
        'ones (floor, main walls) are thinned. With n points the noise part of the offset '
        'along a cluster normal is sigma / sqrt(n), 3 % of the point noise at 1000: far below '
        'the voxel-scale systematic errors, while the nearest-neighbour queries halve. The '
        'rotation stage uses every normal.',
        range=(0, 10_000_000),
    )
    max_step_scale: float = setting(
        16.0,
        'Largest factor by which consecutive refinement steps in the same direction are '
        'lengthened (doubled per step once the gate is at its floor; reversing steps are '
        'halved); 1 disables it.',
        range=(1.0, 1024.0),
    )


@dataclass(frozen=True)
class SearchConfig(Section, prefix='search.'):
    """Start-free rotation search from the two clouds' normal-mixture summaries."""

    mode: SearchMode = setting(
        SearchMode.AUTO,
        "When register() searches SO(3) instead of starting only from init: 'auto' when no "
        "init is given (the odometry searches when a step is doubtful), 'always', 'never'.",
    )
    twist_step_deg: float = setting(
        5.0,
        'Step of the twist grid about each pair of aligned cluster means (deg). The EM '
        'started from a hypothesis converges from about a quarter of a cluster spread; '
        'hypotheses within half a step of the truth reach it.',
        range=(0.5, 90.0),
    )
    candidates: int = setting(
        6,
        'Distinct best hypotheses refined by the EM and verified on the points. Symmetric '
        'scenes give their twins equal summary scores (a room has up to 4 about the vertical, '
        'a corridor 2 per axis), so this must exceed the twins of one axis.',
        range=(1, 100),
    )
    min_separation_deg: float = setting(
        10.0,
        'Hypotheses closer than this (deg) count as one: twice the twist step, so two grid '
        'neighbours of one peak are not both refined.',
        range=(0.0, 180.0),
    )
    ambiguity_ratio: float = setting(
        0.9,
        'Another pose, distinct from the best (its points move by more than twice the fit '
        'distance gate), that fits at least this share of the best fit makes the result '
        'ambiguous: less than a tenth of the matched surfaces tells the two apart.',
        range=(0.0, 1.0),
    )


@dataclass(frozen=True)
class KentRegConfig(Section):
    """All settings of the registrar and the odometry.

    ``mode='paper'`` runs the recipe of Fahandezh-Saadi et al. as written (per-cluster EM on
    separately clustered clouds, rotation averaging, centroid translation); the ablation
    switches marked 'Robust mode' are ignored there. ``mode='robust'`` (default) is the
    improved pipeline; each of its ideas has a switch so benchmarks can show ablations.
    """

    mode: Mode = setting(
        Mode.ROBUST,
        "'robust' (default) or 'paper' (the paper's recipe as written).",
    )
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    normals: NormalsConfig = field(default_factory=NormalsConfig)
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    em: EMConfig = field(default_factory=EMConfig)
    translation: TranslationConfig = field(default_factory=TranslationConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)

    def check(self) -> None:
        hints = get_type_hints(KentRegConfig)
        for f in fields(self):
            value, kind = getattr(self, f.name), hints[f.name]
            if isinstance(kind, type) and is_dataclass(kind) and not isinstance(value, kind):
                raise ConfigError(f'Expected `{f.name}` to be a {kind.__name__}, got {value!r}.')

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> KentRegConfig:
        """Build a config from a nested and/or dotted mapping; unknown keys are an error."""
        return _from_mapping(cls, nest_keys(data), '')

    def to_dict(self) -> dict[str, Any]:
        """Nested plain-dict form (YAML-ready: enumerations as their strings)."""
        return nest_keys(self.to_flat_dict())

    def to_flat_dict(self) -> dict[str, Any]:
        """Flat ``{'em.max_iterations': 50, ...}`` form (ROS parameter names; plain values)."""
        return {name: plain_value(value) for name, value, _ in iter_fields(self)}

    def with_updates(self, updates: Mapping[str, Any]) -> KentRegConfig:
        """A copy with dotted or nested overrides applied (validated)."""
        merged = self.to_flat_dict()
        flat_updates = flatten_keys(nest_keys(updates))
        unknown = sorted(set(flat_updates) - set(merged))
        if unknown:
            raise ConfigError(
                f'Unknown configuration key(s) {unknown}; valid keys are {sorted(merged)}.'
            )
        merged.update(flat_updates)
        return KentRegConfig.from_dict(merged)

    @classmethod
    def paper(cls) -> KentRegConfig:
        """The paper's recipe."""
        return replace(cls(), mode=Mode.PAPER)


def _valid_names(cls: type) -> list[str]:
    return [name for name, _, _ in iter_fields(cls())]


def _from_mapping(cls: type, data: Mapping[str, Any], prefix: str) -> Any:
    hints = get_type_hints(cls)
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        root = KentRegConfig if prefix == '' else cls
        valid = _valid_names(root) if root is KentRegConfig else sorted(known)
        raise ConfigError(
            f'Unknown configuration key(s) {[prefix + k for k in unknown]}; '
            f'valid keys are {valid}.'
        )
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        hint = hints[name]
        full = prefix + name
        if isinstance(hint, type) and is_dataclass(hint):
            if not isinstance(value, Mapping):
                raise ConfigError(f'Expected `{full}` to be a mapping, got {value!r}.')
            kwargs[name] = _from_mapping(hint, value, full + '.')
        else:
            kwargs[name] = value  # coerced and validated by the section itself
    return cls(**kwargs)
