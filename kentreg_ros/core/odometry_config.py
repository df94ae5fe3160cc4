"""The settings of the scan-to-model odometry (``odometry.*`` of the research config,
:class:`~kentreg_ros.core.config.KentRegConfig`) and the enumerations of their choices: the
model, the deskewing and how per-point times are read. Apart from the registration's sections,
as :mod:`~kentreg_ros.core.localization_config` is: the odometry's own concern."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from kentreg_ros.core.fields import Section, setting


class Model(StrEnum):
    """What the odometry registers each scan against."""

    PREVIOUS_SCAN = 'previous_scan'
    LOCAL_MAP = 'local_map'


class Deskew(StrEnum):
    """Whether the odometry deskews the scans that carry per-point times."""

    AUTO = 'auto'
    ON = 'on'
    OFF = 'off'


class TimeUnit(StrEnum):
    """Unit of a per-point time field (``auto``: from the field, then from the values)."""

    AUTO = 'auto'
    S = 's'
    MS = 'ms'
    US = 'us'
    NS = 'ns'


class TimeReference(StrEnum):
    """What a per-point time is counted from: the scan's stamp (``relative``: the driver's zero,
    usually the sweep start, which most drivers also stamp) or the stamp's own clock
    (``absolute``); ``auto``: from the field, then from the values."""

    AUTO = 'auto'
    RELATIVE = 'relative'
    ABSOLUTE = 'absolute'


@dataclass(frozen=True)
class OdometryConfig(Section, prefix='odometry.'):
    """Scan-to-model pose integration: the model is the previous scan or a local map."""

    model: Model = setting(
        Model.PREVIOUS_SCAN,
        'What each scan is registered against: the previous scan (previous_scan, the design '
        "card's model) or a voxel map of the recent accepted scans around the sensor "
        '(local_map). A map holds surfaces the previous scan saw at a grazing angle or not at '
        'all, and a pose error of one step is not handed on as the model of the next, so drift '
        'grows more slowly; it costs the map upkeep and a larger target per scan.',
    )
    map_voxel_size: float = setting(
        0.0,
        'Voxel edge of the local map (m); 0 takes the voxel size of the first scan, so the map '
        "has a scan's sampling resolution and the correspondence gates, which are set from the "
        'voxel size, mean the same against the map as against a scan. Twice that edge made a '
        'step 13-25 % cheaper but lost accuracy on swept, deskewed sequences (simulated: ATE '
        "1.1x the previous scan's instead of 0.7x).",
        range=(0.0, 10.0),
    )
    map_points_per_voxel: int = setting(
        1,
        'Points a local-map voxel keeps: the first to arrive take the places, and every later '
        'point is averaged into the nearest of them, so a surface seen again and again is '
        "held by the mean of its samples rather than by one scan's. With voxels of the scan "
        "size, one keeps the map at a scan's sampling density; as it covers all the sensor saw "
        "within its reach, it holds 2.5-5 scans' worth of points, and the neighbour index it "
        'needs each step grows with it. More keep both surfaces where a voxel '
        'straddles an edge, at a proportional cost.',
        range=(1, 20),
    )
    map_radius: float = setting(
        0.0,
        'Local-map points farther than this from the sensor are dropped (m); 0 uses the reach '
        'of the latest accepted scan (its farthest kept point): what lies beyond the sensor '
        "range cannot overlap the next scan. The map's memory is bounded by this ball.",
        range=(0.0, 10000.0),
    )
    constant_velocity: bool = setting(
        True,
        'Start each registration from the last accepted motion (scaled to the time gap); a '
        'step that fell back never feeds it.',
    )
    deskew: Deskew = setting(
        Deskew.AUTO,
        "Move every point to the scan stamp's time with the motion of the sweep (constant "
        'velocity, iterated with the registration) when the scans carry per-point times '
        '(auto), always (on: warns once when they do not), or never (off).',
    )
    point_time_unit: TimeUnit = setting(
        TimeUnit.AUTO,
        'Unit of the per-point time field: auto reads it from the field (name and datatype of '
        'the common drivers: Ouster t and Livox CustomMsg offset_time uint32 ns, Velodyne time '
        'float32 s, a float64 timestamp absolute s from Hesai/Robosense or absolute ns from '
        "livox_ros_driver2's PointCloud2), then from the values (the unit that makes them a "
        'sweep of at most 2 s around the stamp, which also tells those s from ns); s, ms, us or '
        'ns state it for a driver that does something else.',
    )
    point_time_reference: TimeReference = setting(
        TimeReference.AUTO,
        "What the per-point times count from: relative (the scan stamp, i.e. the driver's "
        'zero, usually the sweep start), absolute (the clock of the stamp), or auto (from the '
        'field, then from the values). Times that are no sweep around the stamp in the unit '
        'and reference used are not used: that scan is not deskewed, with one warning.',
    )
    max_angular_speed_deg: float = setting(
        360.0,
        'Fastest plausible turn of the sensor (deg/s); a step turning more than this times its '
        'time gap is rejected. One turn per second: beyond hand-held sweeps, vehicles and '
        'most aerial platforms.',
        range=(1.0, 100000.0),
    )
    max_linear_speed: float = setting(
        50.0,
        'Fastest plausible motion of the sensor (m/s); a step moving more than this times its '
        'time gap is rejected. 180 km/h: beyond the road vehicles LiDAR odometry runs on.',
        range=(0.01, 10000.0),
    )
    doubt_ratio: float = setting(
        0.7,
        'A step whose fit (share of points landing on matching surfaces) is below this share '
        'of the median fit of the last accepted steps (of 1, the best fit there is, before the '
        'first accepted step) is doubtful: the zero-motion start and the start-free search are '
        'tried too and the best fit wins. Overlap, and so the fit, changes slowly from scan to '
        'scan, while a wrong minimum loses whole families of surfaces (measured: right results '
        'fit 0.70-0.92, wrong ones at most 0.50). Searching costs time, not accuracy, so the '
        'margin errs toward searching.',
        range=(0.0, 1.0),
    )
    fit_window: int = setting(
        10,
        'Accepted steps whose fits form the median doubt_ratio is applied to (a few seconds '
        'of a 2-10 Hz sensor: long enough to be stable, short enough to follow a scene change).',
        range=(1, 1000),
    )
    min_fit: float = setting(
        0.1,
        'A step whose best fit is below this (fewer than a tenth of the points land on a '
        'matching surface: the scans barely overlap) falls back to the prediction.',
        range=(0.0, 1.0),
    )
