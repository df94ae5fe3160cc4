"""Localization in a saved map: where a scan is in it, or that it cannot say.

:class:`PointMap` prepares a point-cloud map once (normals, their Kent mixture, an index, the
translation search's spectra); :func:`localize` places one scan, with or without a start;
:class:`Localizer` tracks a run through the map with the odometry and relocalizes when lost.
"""

from kentreg_ros.core.localization.localize import (
    Candidate,
    LocalizationResult,
    LocalizationStatus,
    free_space_violation,
    localize,
    register_in_map,
)
from kentreg_ros.core.localization.pointmap import PointMap, SearchGrid
from kentreg_ros.core.localization.search import Window
from kentreg_ros.core.localization.tracker import Localizer, TrackingState, TrackStep

__all__ = [
    'Candidate',
    'Localizer',
    'LocalizationResult',
    'LocalizationStatus',
    'PointMap',
    'SearchGrid',
    'TrackStep',
    'TrackingState',
    'Window',
    'free_space_violation',
    'localize',
    'register_in_map',
]
