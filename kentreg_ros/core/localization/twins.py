"""The box twins of a pose: where a narrow view of a room fits about as well when turned.

A room is a box: its walls, floor and ceiling are three perpendicular pairs of planes, and a
scan turned by any of the box's 23 symmetries (besides the identity) lands its normals on the
same families of surfaces. A scan that sees all around tells the twins apart by what it sees
on every side; a narrow one (a 70 deg sensor sees a wall, the floor, a corner) often does not:
the mixtures' overlap ranks its twins above the truth, the search proposes only some of them,
and a wrong twin that passes the fit and free-space gates is localized with no rival in the
list to make it ambiguous. Measured on the Livox Avia keyframes of a small room (map of the even
keyframes, odd ones held out): the true rotation ranked 122nd of the twist hypotheses, below a
dozen twins; the scans localized wrong were all box twins of the truth (89-91, 123 and 179 deg
off, 2.4-10.7 m away) with fits 0.32-0.59, and the truth, registered, fitted about as well
(0.60 against the 0.59 of its 91 deg twin).

So the search of a narrow scan takes every box twin of its best rotation as a rotation
hypothesis (:func:`twin_rotations`: the correlation of the normal channels, not the mixtures'
overlap, tells them apart), and before it is localized no twin of its answer may outscore the
answer's own correlation peak (:func:`~.localize.localize`). When the answer's rotation is
not among the twins searched, they are searched then (:func:`twin_starts`) and their best
starts registered with the other candidates: one that fits ``search.ambiguity_ratio`` as well
makes the result ambiguous, one that fits clearly better is the answer. The twins of a twin
are the same set, so the answer's twins are covered either way.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core.config import KentRegConfig
from kentreg_ros.core.geometry import rotation_angle
from kentreg_ros.core.localization.pointmap import PointMap
from kentreg_ros.core.localization.search import Hypothesis, Window, closer_start, translations
from kentreg_ros.core.registration.search import mixture_overlap
from kentreg_ros.core.scan import PreparedScan
from kentreg_ros.core.scan.clusters import ModelClusters

FloatArray = NDArray[np.float64]

#: Two normal directions of the map within this many degrees of perpendicular are two axes of
#: its box frame.
BOX_AXIS_TOLERANCE_DEG = 30.0
#: A scan whose ray directions have a mean resultant length above this looks one way: its
#: rays lie within a cone of about +-60 deg (a Livox Avia's 70 x 77 deg view gives ~0.9, a
#: spinning LiDAR's 360 deg ~0.1-0.3). Such a scan's twins are checked.
NARROW_VIEW = 0.5
#: Twins whose mixtures' overlap is farther below the answer's than this (log) are not searched
#: (:func:`twin_starts`).
TWIN_OVERLAP_MARGIN = 0.4
#: Twin starts registered, best correlation first: the truth's peak was the second highest of
#: the 23 twins' on the quick_shack keyframe measured.
TWINS_REGISTERED = 3


def is_narrow(scan: PreparedScan) -> bool:
    """Whether ``scan`` looks one way (:data:`NARROW_VIEW`)."""
    r = np.linalg.norm(scan.points, axis=1)
    ok = r > 0.0
    if not ok.any():
        return False
    rays = scan.points[ok] / r[ok, None]
    return float(np.linalg.norm(rays.mean(axis=0))) > NARROW_VIEW


def box_twins(mixture: ModelClusters) -> list[FloatArray]:
    """The 23 rotations (map frame, besides the identity) that map the box frame of
    ``mixture`` onto itself: its heaviest normal direction, the heaviest within
    :data:`BOX_AXIS_TOLERANCE_DEG` of perpendicular to it, and their cross product, each turned
    onto one of the three, either way. None when no two directions are that perpendicular."""
    order = np.argsort(-np.asarray(mixture.weights))
    centers = np.asarray(mixture.centers, dtype=np.float64)[order]
    if len(centers) < 2:
        return []
    a = centers[0] / np.linalg.norm(centers[0])
    near = np.abs(centers[1:] @ a) <= np.sin(np.radians(BOX_AXIS_TOLERANCE_DEG))
    if not near.any():
        return []
    b = centers[1:][int(np.argmax(near))]
    b = b - (b @ a) * a
    b /= np.linalg.norm(b)
    frame = np.stack([a, b, np.cross(a, b)], axis=1)
    out: list[FloatArray] = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            P = np.zeros((3, 3))
            P[range(3), perm] = signs
            if np.linalg.det(P) > 0.0 and not np.allclose(P, np.eye(3)):
                out.append(frame @ P @ frame.T)
    return out


def twin_rotations(
    scan: PreparedScan,
    pmap: PointMap,
    R_map_scan: FloatArray,
    config: KentRegConfig,
    *,
    start: FloatArray | None = None,
    window: Window | None = None,
) -> list[FloatArray]:
    """The box twins of ``R_map_scan`` (within the window, if any) that the mixtures' overlap
    cannot rule out: those whose overlap with the map's mixture lies within
    :data:`TWIN_OVERLAP_MARGIN` (log) of the best of the 24 (the rotation and its twins).

    For the search of a narrow scan (:func:`~.localize.localize`): the overlap cannot tell a
    narrow view's twins apart, the correlation of the normal channels can. Measured on the
    quick_shack room (map of the even keyframes, 60 odd ones from no start): the search's
    rotations missed the truth in 33 of the 36 scans not localized, every time by a box twin
    of its best rotation (87-95, 118-124 or 177-179 deg). The truth's overlap ranked 0-16th of
    its 24, while its best correlation peak outscored those of all 23 twins in 56 of the 60
    scans (tied in 2, 4 % below in 2); the twins kept by the margin came within 9 deg of the
    truth in 59 of the 60 (the other's best rotation lay 7 deg off the room's box frame, and
    its twin nearest the truth 0.41 below the best overlap)."""
    return _kept_twins(scan, pmap, R_map_scan, config, start, window, of_best=True)


def _kept_twins(
    scan: PreparedScan,
    pmap: PointMap,
    R_map_scan: FloatArray,
    config: KentRegConfig,
    start: FloatArray | None,
    window: Window | None,
    *,
    of_best: bool,
) -> list[FloatArray]:
    """The box twins of ``R_map_scan`` within the window (if any) whose overlap with the map's
    mixture lies within :data:`TWIN_OVERLAP_MARGIN` of the best of the 24 (``of_best``) or of
    ``R_map_scan``'s own."""
    twins = box_twins(pmap.clusters)
    if not twins:
        return []
    cap = 1.0 / np.radians(config.search.twist_step_deg) ** 2
    turned = np.stack([Q @ R_map_scan for Q in twins])
    overlap = mixture_overlap(
        np.concatenate([R_map_scan[None], turned]), scan.clusters, pmap.clusters, cap
    )
    floor = (overlap.max() if of_best else overlap[0]) - TWIN_OVERLAP_MARGIN
    out: list[FloatArray] = []
    for R0, score in zip(turned, overlap[1:], strict=True):
        if score < floor:
            continue
        if start is not None and window is not None:
            if rotation_angle(start[:3, :3].T @ R0) > np.radians(window.angle_deg):
                continue
        out.append(R0)
    return out


def twin_starts(
    scan: PreparedScan,
    pmap: PointMap,
    R_map_scan: FloatArray,
    config: KentRegConfig,
    *,
    start: FloatArray | None = None,
    window: Window | None = None,
) -> list[Hypothesis]:
    """The starts of the box twins of ``R_map_scan`` (within the window, if any) that the
    mixtures' overlap cannot rule out: for each its best translation peak, the
    :data:`TWINS_REGISTERED` best peaks kept.

    A twin whose overlap with the map's mixture is more than :data:`TWIN_OVERLAP_MARGIN` (log)
    below the answer's lands the scan's normals on clearly rarer directions of the map (the
    ground of a street turned onto a wall) and is not searched: measured on the quick_shack
    room, the truth's overlap lay at most 0.33 below one of its twins'; on hku_2 (outdoors)
    5-8 of the 23 twins are within the margin. Every other twin is searched, even one near a
    rotation the search started from: a start that did not converge does not cover its twin
    (the true rotation of a quick_shack keyframe lay within 10 deg of a search start whose
    registrations failed; from its twin, 3 deg and 0.7 m off, the registration reached it).
    The twin of a registered rotation is kept as it is: refined by the EM against the whole
    map's mixture it drifts (3 deg from the truth before, 4.2 after), and the registration
    corrects the rest."""
    out: list[Hypothesis] = []
    for R0 in _kept_twins(scan, pmap, R_map_scan, config, start, window, of_best=False):
        out += translations(scan, R0, pmap, 1, start=start, window=window)
    out.sort(key=lambda h: -h.score)
    return [closer_start(scan, pmap, h) for h in out[:TWINS_REGISTERED]]
