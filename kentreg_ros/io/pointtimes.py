"""Per-point time fields of a cloud: which field holds the times, and moving absolute times
with a new stamp (a player's loop or re-stamping)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros.core import (
    ImplausibleTimesError,
    PointTimes,
    TimeReference,
    TimeUnit,
    sweep_times,
)

#: Names of per-point time fields written by common LiDAR drivers; kept like any other field.
POINT_TIME_FIELDS = ('t', 'time', 'timestamp', 'offset_time', 'time_offset')


def point_time_field(extras: Mapping[str, Any] | None) -> PointTimes | None:
    """The per-point times among a cloud's extra fields (the first of
    :data:`POINT_TIME_FIELDS` present, one value per point) with the field's name, or None.

    The values keep the datatype the message gave them: with the name it tells the
    odometry the unit and reference
    (:data:`kentreg_ros.core.odometry.deskew.DRIVER_TIME_FIELDS`)."""
    for name in POINT_TIME_FIELDS:
        if extras and name in extras:
            values = np.asarray(extras[name])
            if values.ndim == 1 or (values.ndim == 2 and values.shape[1] == 1):
                return PointTimes(values.ravel(), name)
    return None


def shift_point_times(
    extras: Mapping[str, NDArray[Any]], stamp_ns: int, new_stamp_ns: int
) -> dict[str, NDArray[Any]]:
    """``extras`` for the scan stamped ``stamp_ns`` when it is stamped ``new_stamp_ns``
    instead (a player's loop or re-stamping): an absolute per-point time field (as
    :func:`~kentreg_ros.core.odometry.deskew.sweep_times` reads it against the old stamp: a
    Hesai/Robosense or livox_ros_driver2 ``timestamp``) moves by the same amount, in its own
    unit and datatype, so it stays a sweep around the new stamp; every other field, and
    relative or unreadable times, are kept as they are.

    Parameters
    ----------
    extras : dict of str to ndarray
        The scan's per-point fields.
    stamp_ns, new_stamp_ns : int
        The scan's stamp and the stamp it is given, nanoseconds.

    Returns
    -------
    dict of str to ndarray
        A new dict; the shifted field is a new array, the others are ``extras``' own.
    """
    out = dict(extras)
    times = point_time_field(extras) if new_stamp_ns != stamp_ns else None
    if times is None:
        return out
    try:
        found = sweep_times(times.values, stamp_ns, field=times.field)
    except ImplausibleTimesError:
        return out
    if found.reference is not TimeReference.ABSOLUTE:
        return out
    values = times.values
    delta_ns = int(new_stamp_ns) - int(stamp_ns)
    unit_ns = {TimeUnit.S: 10**9, TimeUnit.MS: 10**6, TimeUnit.US: 10**3}.get(found.unit, 1)
    if values.dtype.kind in 'iu':  # integer times: exact in ns, rounded in coarser units
        step = round(delta_ns / unit_ns)
        shifted = (values.astype(np.int64) + step).astype(values.dtype)
    else:
        shifted = (values + delta_ns / unit_ns).astype(values.dtype)
    out[times.field] = shifted.reshape(np.shape(extras[times.field]))
    return out
