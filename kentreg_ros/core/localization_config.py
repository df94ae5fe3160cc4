"""The settings of localization in a saved map (``localization.*`` of the research config,
:class:`~kentreg_ros.core.config.KentRegConfig`), apart from its other sections so that the
localization package can import the configuration without a cycle."""

from __future__ import annotations

from dataclasses import dataclass

from kentreg_ros.core.fields import Section, setting


@dataclass(frozen=True)
class LocalizationConfig(Section, prefix='localization.'):
    """Localization of a scan in a saved point-cloud map (:mod:`kentreg_ros.core.localization`)."""

    map_voxel_size: float = setting(
        0.2,
        'Voxel edge of the prepared map (m): as fine as the automatic voxel of most scans '
        '(0.1-0.5 m), so that the registration against the map keeps its resolution; finer '
        'maps cost memory and time in proportion, not accuracy (the gates follow the coarser '
        'of the scan and the map).',
        range=(0.02, 10.0),
    )
    grid_cells: int = setting(
        1 << 20,
        'Cells of the translation search grid (map extent plus scan extent) at most: its cell '
        'grows past 1 m to stay under this, which bounds the memory (a complex64 spectrum per '
        'normal axis) and the time of a search whatever the size of the map. A coarser cell '
        'only places the candidates less precisely; the registration from each finishes.',
        range=(1 << 14, 1 << 26),
    )
    rotations: int = setting(
        8,
        'Distinct rotation hypotheses (from the Kent mixtures of the scan and the map) whose '
        'translations are searched: a room has up to 4 twins about the vertical, and a '
        'narrow view fewer clusters to tell them apart.',
        range=(1, 64),
    )
    peaks: int = setting(
        3,
        'Translations kept per rotation (the best correlation peaks, at least 2 cells apart): '
        'repeated structure (a row of pillars, a corridor) gives a few peaks of similar height.',
        range=(1, 32),
    )
    refined: int = setting(
        8,
        'Candidates (rotation and translation) registered against the map, best correlation '
        'first: the one that fits best is judged by the gates.',
        range=(1, 256),
    )
    min_fit: float = setting(
        0.3,
        'A pose is localized only when at least this share of the scan lands on matching map '
        'surfaces (the balanced fit): below it the map explains too little of the scan to '
        'vouch for a pose (right poses fitted 0.42-0.96 on the BALM and Avia keyframes).',
        range=(0.0, 1.0),
    )
    max_violation: float = setting(
        0.3,
        "A pose is refused when the scan's rays pass through more than this share of the map "
        'points they reach (by more than 5 % of the range): the scan saw empty space where '
        'the map has a surface. At the reference poses 0.06 (BALM), 0.12 (Avia outdoors) and '
        'up to 0.27 (a small room with fast hand-held turns: moving people, a smeared map; one '
        'keyframe there 0.31, refused); wrong poses mostly 0.3-0.8. A pose that passes still '
        'needs no distinct rival within search.ambiguity_ratio of its fit.',
        range=(0.0, 1.0),
    )
    min_visible: int = setting(
        100,
        "Map points in the scan's view (within its reach and along its rays) a pose needs "
        'for its free-space test to say anything; a pose that sees fewer is refused.',
        range=(0, 10_000_000),
    )
    agreement: int = setting(
        3,
        'Consecutive scans (chained by the odometry) whose localizations must agree before a '
        'pose found without a start is taken: a twin or a wrong place agrees with itself '
        'over the motion far less often than the right place.',
        range=(1, 100),
    )
    tracking_distance: float = setting(
        0.5,
        'A tracked pose may move from its prediction (the odometry) by this much (m) in one '
        'scan; a larger correction needs the gates of a relocalization (never a silent jump).',
        range=(0.0, 100.0),
    )
    tracking_angle_deg: float = setting(
        5.0,
        'A tracked pose may turn from its prediction by this much (deg) in one scan; a '
        'larger correction needs the gates of a relocalization.',
        range=(0.0, 180.0),
    )
