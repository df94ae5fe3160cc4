"""Livox inputs as users get them, deskewed: livox_ros_driver2's PointCloud2 (a float64
``timestamp`` of absolute nanoseconds at an unaligned offset) and ``CustomMsg`` bags (rosbag2
sqlite3 and MCAP, ROS 1), written with rosbags' own Writers from a room seen by a sensor that
moves during each sweep."""

from __future__ import annotations

import contextlib
import io
import logging
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scenes import box_room
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from kentreg_ros.core import InvalidPointCloudError, KentRegConfig, Odometry
from kentreg_ros.core.geometry import hat
from kentreg_ros.core.odometry.deskew import ImplausibleTimesError, deskew, sweep_times
from kentreg_ros.io.errors import BagError
from kentreg_ros.io.livox import (
    CUSTOM_MSG_TYPES,
    custom_msg_to_array,
    custom_msg_types,
    definition_problem,
    live_custom_msg_hint,
)
from kentreg_ros.io.pointcloud2 import FLOAT32, FLOAT64, UINT8, pointcloud2_to_array
from kentreg_ros.io.pointtimes import point_time_field, shift_point_times
from kentreg_ros.io.sources import SkippedScan, open_scan_source

rosbags = pytest.importorskip('rosbags', reason='rosbags is not installed (pip install -e .[io])')
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

DRIVER2 = 'livox_ros_driver2/msg/CustomMsg'
DRIVER1 = 'livox_ros_driver/msg/CustomMsg'
PC2 = 'sensor_msgs/msg/PointCloud2'
TOPIC = '/livox/lidar'
#: A PTP-synchronised Livox: stamps on the epoch, in nanoseconds.
T0 = 1_700_000_000_123_456_789
PERIOD_NS = 100_000_000  # livox_ros_driver2's publish_freq 10 Hz
#: Livox points come in packets of one time; 200 packet times per sweep, 0.5 ms apart.
PACKET_NS = 500_000
#: 1 m/s forward and 30 deg/s of yaw, constant, in the sensor frame (test_deskew's motion).
TWIST = np.array([0.0, 0.0, np.radians(30.0), 1.0, 0.0, 0.0])
POINTS_PER_SCAN = 6000


def _store(stores: Stores, package: str) -> Any:
    store = get_typestore(stores)
    store.register(custom_msg_types(package))
    return store


JAZZY = _store(Stores.ROS2_JAZZY, 'livox_ros_driver2')
NOETIC = _store(Stores.ROS1_NOETIC, 'livox_ros_driver')


def _pose(t_s: float) -> np.ndarray:
    """The sensor's pose in the room at ``t_s`` from the first stamp: exactly exp(t xi)."""
    m = np.zeros((4, 4))
    m[:3, :3] = hat(TWIST[:3])
    m[:3, 3] = TWIST[3:]
    return np.asarray(expm(t_s * m))


@dataclass(frozen=True)
class Sweep:
    """One scan: its stamp (the first packet's time) and pose, the points as measured (float32,
    each in the sensor frame of its packet's time), their offsets from the stamp (uint32 ns),
    and the same points where they are at the stamp (what deskewing must give back)."""

    stamp_ns: int
    T_world_sensor: np.ndarray
    points: np.ndarray
    offsets: np.ndarray
    at_stamp: np.ndarray
    reflectivity: np.ndarray
    line: np.ndarray


def _sweep(world: np.ndarray, index: int, rng: np.random.Generator) -> Sweep:
    start = index * PERIOD_NS * 1e-9
    q = world[rng.choice(len(world), POINTS_PER_SCAN, replace=False)]
    packet = np.sort(rng.integers(0, PERIOD_NS // PACKET_NS, POINTS_PER_SCAN))
    measured = np.empty_like(q)
    for k in np.unique(packet):  # one pose per packet time: exact
        T = _pose(start + k * PACKET_NS * 1e-9)
        rows = packet == k
        measured[rows] = (q[rows] - T[:3, 3]) @ T[:3, :3]
    T = _pose(start)
    return Sweep(
        stamp_ns=T0 + index * PERIOD_NS,
        T_world_sensor=T,
        points=measured.astype(np.float32),
        offsets=(packet * PACKET_NS).astype(np.uint32),
        at_stamp=(q - T[:3, 3]) @ T[:3, :3],
        reflectivity=rng.integers(0, 256, POINTS_PER_SCAN).astype(np.uint8),
        line=(np.arange(POINTS_PER_SCAN) % 6).astype(np.uint8),
    )


@pytest.fixture(scope='module')
def sweeps() -> list[Sweep]:
    rng = np.random.default_rng(7)
    world = box_room(rng, 60_000, size=(12.0, 8.0, 3.0), boxes=4)
    return [_sweep(world, i, rng) for i in range(6)]


# --- writing bags as the drivers do ----------------------------------------------------------


def _ros1_stamp(timebase_ns: int) -> tuple[int, int]:
    """``ros::Time(timebase / 1000000000.0)``, as livox_ros_driver stamps its header: through
    a double of seconds, so up to a few hundred ns off ``timebase``."""
    t = timebase_ns / 1e9
    sec = int(np.floor(t))
    return sec, int(round((t - sec) * 1e9))


def _custom_msg(
    store: Any, msgtype: str, sweep: Sweep, *, point_num: int | None = None, ros1: bool = False
) -> Any:
    types = store.types
    package = msgtype.split('/')[0]
    point = types[f'{package}/msg/CustomPoint']
    points = [
        point(
            offset_time=int(o), x=float(p[0]), y=float(p[1]), z=float(p[2]),
            reflectivity=int(r), tag=0x10, line=int(ln),
        )
        for o, p, r, ln in zip(
            sweep.offsets, sweep.points, sweep.reflectivity, sweep.line, strict=True
        )
    ]  # fmt: skip
    if ros1:
        sec, nanosec = _ros1_stamp(sweep.stamp_ns)
        extra = {'seq': 0}
    else:
        sec, nanosec = divmod(sweep.stamp_ns, 1_000_000_000)
        extra = {}
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
        frame_id='livox_frame',
        **extra,
    )
    return types[msgtype](
        header=header,
        timebase=sweep.stamp_ns,
        point_num=len(points) if point_num is None else point_num,
        lidar_id=0,
        rsvd=np.zeros(3, np.uint8),
        points=points,
    )


def _write_custom_bag(
    path: Path, sweeps: list[Sweep], storage: str, *, point_nums: dict[int, int] | None = None
) -> Path:
    """A Livox recording, as ``ros2 bag record`` (rosbag2) or rosbag (ROS 1) leaves it: the
    CustomMsg topic beside the IMU's."""
    point_nums = point_nums or {}
    if storage == 'ros1':
        path = path.with_suffix('.bag')
        with Writer1(path) as writer:
            conn = writer.add_connection(TOPIC, DRIVER1, typestore=NOETIC)
            writer.add_connection('/livox/imu', 'sensor_msgs/msg/Imu', typestore=NOETIC)
            for i, sweep in enumerate(sweeps):
                msg = _custom_msg(NOETIC, DRIVER1, sweep, point_num=point_nums.get(i), ros1=True)
                writer.write(conn, sweep.stamp_ns, NOETIC.serialize_ros1(msg, DRIVER1))
        return path
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conn = writer.add_connection(TOPIC, DRIVER2, typestore=JAZZY)
        writer.add_connection('/livox/imu', 'sensor_msgs/msg/Imu', typestore=JAZZY)
        for i, sweep in enumerate(sweeps):
            msg = _custom_msg(JAZZY, DRIVER2, sweep, point_num=point_nums.get(i))
            writer.write(conn, sweep.stamp_ns, JAZZY.serialize_cdr(msg, DRIVER2))
    return path


#: livox_ros_driver2's LivoxPointXyzrtlt (``#pragma pack(1)``): 26 bytes, timestamp at 18.
DRIVER2_POINT = np.dtype(
    {
        'names': ['x', 'y', 'z', 'intensity', 'tag', 'line', 'timestamp'],
        'formats': ['<f4', '<f4', '<f4', '<f4', 'u1', 'u1', '<f8'],
        'offsets': [0, 4, 8, 12, 16, 17, 18],
        'itemsize': 26,
    }
)


def _driver2_pointcloud2(sweep: Sweep, *, times_s: bool = False) -> Any:
    """The PointCloud2 livox_ros_driver2 publishes with xfer_format 0 (Lddc::
    InitPointcloud2MsgHeader): fields at the struct's packed offsets, each point's absolute
    time as a double of nanoseconds (``times_s``: of seconds, as Hesai and Robosense do)."""
    types = JAZZY.types
    rec = np.zeros(len(sweep.points), DRIVER2_POINT)
    for axis, c in enumerate('xyz'):
        rec[c] = sweep.points[:, axis]
    rec['intensity'] = sweep.reflectivity
    rec['line'] = sweep.line
    absolute_ns = sweep.stamp_ns + sweep.offsets.astype(np.int64)
    rec['timestamp'] = absolute_ns * 1e-9 if times_s else absolute_ns.astype(np.float64)
    kinds = [FLOAT32] * 4 + [UINT8, UINT8, FLOAT64]
    fields = [
        types['sensor_msgs/msg/PointField'](name=name, offset=offset, datatype=kind, count=1)
        for name, offset, kind in zip(
            DRIVER2_POINT.names, (0, 4, 8, 12, 16, 17, 18), kinds, strict=True
        )
    ]
    sec, nanosec = divmod(sweep.stamp_ns, 1_000_000_000)
    return types[PC2](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
            frame_id='livox_frame',
        ),
        height=1,
        width=len(rec),
        fields=fields,
        is_bigendian=False,
        point_step=26,
        row_step=26 * len(rec),
        data=np.frombuffer(rec.tobytes(), np.uint8),
        is_dense=True,
    )


def _write_pointcloud2_bag(path: Path, sweeps: list[Sweep], storage: StoragePlugin) -> Path:
    with Writer(path, version=9, storage_plugin=storage) as writer:
        conn = writer.add_connection(TOPIC, PC2, typestore=JAZZY)
        for sweep in sweeps:
            msg = _driver2_pointcloud2(sweep)
            writer.write(conn, sweep.stamp_ns, JAZZY.serialize_cdr(msg, PC2))
    return path


def _deskew_error(points: np.ndarray, times_s: np.ndarray, sweep: Sweep) -> np.ndarray:
    """How far each point lies from where it is at the stamp, after deskewing with the true
    motion."""
    return np.linalg.norm(deskew(points, times_s, TWIST) - sweep.at_stamp, axis=1)


# --- livox_ros_driver2's PointCloud2 -----------------------------------------------------------


def test_driver2_pointcloud2_is_read_at_its_packed_offsets_with_nanosecond_times(
    sweeps: list[Sweep],
) -> None:
    sweep = sweeps[1]
    msg = _driver2_pointcloud2(sweep)
    assert msg.point_step == 26 and msg.fields[-1].offset == 18  # the driver's layout
    cloud = pointcloud2_to_array(msg)
    np.testing.assert_array_equal(cloud.points, sweep.points)
    np.testing.assert_array_equal(cloud.extras['line'], sweep.line)
    assert cloud.stamp_ns == sweep.stamp_ns and cloud.frame_id == 'livox_frame'
    times = point_time_field(cloud.extras)
    assert times is not None and times.field == 'timestamp' and times.values.dtype == np.float64
    found = sweep_times(times.values, cloud.stamp_ns, field=times.field)
    assert (found.unit, found.reference) == ('ns', 'absolute')
    assert 'livox_ros_driver2 ns: ns by the values' in found.source
    # float64 holds 1.7e18 ns to 256 ns: the offsets come back to that.
    np.testing.assert_allclose(found.seconds, sweep.offsets * 1e-9, rtol=0, atol=3e-7)
    before = np.linalg.norm(cloud.points - sweep.at_stamp, axis=1)
    after = _deskew_error(cloud.points, found.seconds, sweep)
    assert before.max() > 0.05 and after.max() < 1e-4


@pytest.mark.parametrize(
    ('stamp_ns', 'unit', 'to_value'),
    [
        (T0, 'ns', float),  # livox_ros_driver2 on PTP time
        (T0, 's', lambda ns: ns * 1e-9),  # Hesai, Robosense
        (1_234 * 1_000_000_000, 'ns', float),  # a Livox without time sync: its boot clock
        (1_234 * 1_000_000_000, 's', lambda ns: ns * 1e-9),
        (5 * 1_000_000_000, 'ns', float),  # seconds after boot, or a simulation's clock
        (5 * 1_000_000_000, 's', lambda ns: ns * 1e-9),
    ],
)
def test_a_float64_timestamp_is_told_seconds_or_nanoseconds_by_its_values(
    stamp_ns: int, unit: str, to_value: Any
) -> None:
    offsets = np.linspace(0, PERIOD_NS, 1000).astype(np.int64)
    values = np.array([to_value(stamp_ns + int(o)) for o in offsets])  # as the driver rounds
    found = sweep_times(values, stamp_ns, field='timestamp')
    assert (found.unit, found.reference) == (unit, 'absolute')
    np.testing.assert_allclose(found.seconds, offsets * 1e-9, rtol=0, atol=1e-6)


def test_a_stated_unit_and_reference_override_the_float64_timestamp() -> None:
    values = (T0 + np.array([0, 50_000_000])).astype(np.float64)  # absolute ns
    stated = sweep_times(values, T0, field='timestamp', unit='ns', reference='absolute')
    assert stated.source == 'stated'
    np.testing.assert_allclose(stated.seconds, [0.0, 0.05], atol=1e-6)
    with pytest.raises(ImplausibleTimesError, match='no sweep'):  # stated seconds: not guessed
        sweep_times(values, T0, field='timestamp', unit='s')
    relative = sweep_times(np.array([0.0, 5e7]), T0, field='timestamp', reference='relative')
    np.testing.assert_allclose(relative.seconds, [0.0, 0.05])  # a fork writing offsets, stated


# --- CustomMsg bags ----------------------------------------------------------------------------


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap', 'ros1'])
def test_custom_msg_bags_give_points_and_times_that_deskew_exactly(
    sweeps: list[Sweep], tmp_path: Path, storage: str
) -> None:
    bag = _write_custom_bag(tmp_path / 'livox', sweeps[:3], storage)
    source = open_scan_source(bag)  # the one scan topic beside the IMU's
    assert source.topic == TOPIC and len(source) == 3
    scans = list(source)
    for scan, sweep in zip(scans, sweeps, strict=False):
        np.testing.assert_array_equal(scan.points, sweep.points)
        np.testing.assert_array_equal(scan.extras['offset_time'], sweep.offsets)
        np.testing.assert_array_equal(scan.extras['reflectivity'], sweep.reflectivity)
        np.testing.assert_array_equal(scan.extras['line'], sweep.line)
        assert (scan.extras['tag'] == 0x10).all() and scan.frame_id == 'livox_frame'
        times = point_time_field(scan.extras)
        assert (
            times is not None and times.field == 'offset_time' and 'timestamp' not in scan.extras
        )
        found = sweep_times(times.values, scan.stamp_ns, field=times.field)
        assert 'Livox' in found.source
        if storage == 'ros1':  # the header holds timebase through a double of seconds
            assert 0 < abs(scan.stamp_ns - sweep.stamp_ns) < 1000
        else:
            assert scan.stamp_ns == sweep.stamp_ns
        np.testing.assert_allclose(found.seconds, sweep.offsets * 1e-9, rtol=0, atol=1e-6)
        before = np.linalg.norm(scan.points - sweep.at_stamp, axis=1)
        assert (
            before.max() > 0.05 and _deskew_error(scan.points, found.seconds, sweep).max() < 1e-4
        )


def test_a_custom_msg_header_stamped_otherwise_times_its_points_from_timebase(
    sweeps: list[Sweep],
) -> None:
    """A header re-stamped downstream: the points' times are timebase + offset_time, read
    against the stamp; a stamp on another clock leaves them no sweep (not deskewed)."""
    sweep = sweeps[0]
    for shift_ns, plausible in ((-30_000_000, True), (3_600 * 1_000_000_000, False)):
        msg = _custom_msg(JAZZY, DRIVER2, sweep)
        sec, nanosec = divmod(sweep.stamp_ns + shift_ns, 1_000_000_000)
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        cloud = custom_msg_to_array(JAZZY.serialize_cdr(msg, DRIVER2))
        assert cloud.stamp_ns == sweep.stamp_ns + shift_ns
        times = point_time_field(cloud.extras)
        assert times is not None and times.field == 'timestamp'
        assert times.values.dtype == np.float64  # as livox_ros_driver2's PointCloud2 has it
        if plausible:
            found = sweep_times(times.values, cloud.stamp_ns, field=times.field)
            want = (sweep.offsets.astype(np.int64) - shift_ns) * 1e-9
            np.testing.assert_allclose(found.seconds, want, rtol=0, atol=3e-7)
        else:
            with pytest.raises(ImplausibleTimesError, match='no sweep'):
                sweep_times(times.values, cloud.stamp_ns, field=times.field)
    assert (
        'timestamp'
        not in custom_msg_to_array(
            JAZZY.serialize_cdr(_custom_msg(JAZZY, DRIVER2, sweep), DRIVER2)
        ).extras
    )


def test_custom_msg_decoding_agrees_with_rosbags_own_deserialiser(
    sweeps: list[Sweep], tmp_path: Path
) -> None:
    """The numpy view of the serialised points against rosbags' per-point objects, in both
    wire formats (CDR aligns each point to 4 bytes, ROS 1 packs them)."""
    for storage in ('mcap', 'ros1'):
        bag = _write_custom_bag(tmp_path / f'agree_{storage}', sweeps[:1], storage)
        with AnyReader([bag]) as reader:
            ((connection, _, raw),) = list(reader.messages())[:1]
            msg: Any = reader.deserialize(raw, connection.msgtype)
            assert definition_problem(reader.typestore.fielddefs, connection.msgtype) is None
        cloud = custom_msg_to_array(raw, ros1=storage == 'ros1')
        reference = np.array([(p.x, p.y, p.z) for p in msg.points])  # a test may loop
        np.testing.assert_array_equal(cloud.points, reference)
        for name in ('offset_time', 'reflectivity', 'tag', 'line'):
            np.testing.assert_array_equal(
                cloud.extras[name], [getattr(p, name) for p in msg.points]
            )
        assert cloud.frame_id == msg.header.frame_id


def test_custom_msg_points_that_are_not_finite_are_dropped_with_their_fields(
    sweeps: list[Sweep],
) -> None:
    sweep = sweeps[0]
    msg = _custom_msg(JAZZY, DRIVER2, sweep)
    msg.points[3].y = float('nan')
    cloud = custom_msg_to_array(JAZZY.serialize_cdr(msg, DRIVER2), dtype=np.float32)
    assert cloud.n_dropped == 1 and cloud.points.dtype == np.float32
    keep = np.arange(len(sweep.points)) != 3
    np.testing.assert_array_equal(cloud.points, sweep.points[keep])
    np.testing.assert_array_equal(cloud.extras['offset_time'], sweep.offsets[keep])


def test_kentreg_replay_deskews_livox_bags(sweeps: list[Sweep], tmp_path: Path) -> None:
    """kentreg_replay BAG --topic /livox/lidar over a CustomMsg MCAP bag and a bag of the
    driver's PointCloud2: the sweeps are deskewed, and the motion found is at least twice as
    accurate as with deskewing off on the same bags."""
    from kentreg_ros.cli.replay import main

    gt = tmp_path / 'gt_tum.txt'
    truth = np.array([s.T_world_sensor for s in sweeps])
    stamps = np.array([[s.stamp_ns * 1e-9] for s in sweeps])
    quat = Rotation.from_matrix(truth[:, :3, :3]).as_quat()
    np.savetxt(gt, np.hstack([stamps, truth[:, :3, 3], quat]), fmt='%.9f')
    bags = {
        'custom_msg': _write_custom_bag(tmp_path / 'custom', sweeps, 'mcap'),
        'pointcloud2': _write_pointcloud2_bag(tmp_path / 'pc2', sweeps, StoragePlugin.SQLITE3),
    }
    for kind, bag in bags.items():
        errors = {}
        for deskewing in ('auto', 'off'):
            out = tmp_path / f'{kind}_{deskewing}'
            argv = [str(bag), '--topic', TOPIC, '--gt', str(gt), '--out', str(out)]
            argv += ['--no-progress', '--no-plot', '--set', f'odometry.deskew={deskewing}']
            stderr = io.StringIO()
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(stderr):
                assert main(argv) == 0, stderr.getvalue()
            rows = np.loadtxt(out / 'poses_tum.txt', ndmin=2)
            assert len(rows) == len(sweeps)
            T = np.tile(np.eye(4), (len(rows), 1, 1))
            T[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
            T[:, :3, 3] = rows[:, 1:4]
            rel = np.linalg.inv(T[:-1]) @ T[1:]
            rel_true = np.linalg.inv(truth[:-1]) @ truth[1:]
            e_t = np.linalg.norm(rel[:, :3, 3] - rel_true[:, :3, 3], axis=1)
            e_R = Rotation.from_matrix(
                np.transpose(rel_true[:, :3, :3], (0, 2, 1)) @ rel[:, :3, :3]
            ).magnitude()
            errors[deskewing] = float(np.median(e_t)), float(np.degrees(np.median(e_R)))
        (t_on, r_on), (t_off, r_off) = errors['auto'], errors['off']
        # Not deskewed is only a few times worse: two sweeps smeared alike by a steady motion
        # still register nearly right, the smear being in both.
        assert t_on < 0.002 and r_on < 0.03, (kind, errors)
        assert t_on < 0.5 * t_off and r_on < 0.5 * r_off, (kind, errors)


# --- bad input -------------------------------------------------------------------------------


def test_a_custom_msg_whose_point_num_disagrees_is_skipped_and_named(
    sweeps: list[Sweep], tmp_path: Path
) -> None:
    bag = _write_custom_bag(tmp_path / 'bad', sweeps[:3], 'mcap', point_nums={1: 10})
    source = open_scan_source(bag)
    entries = list(source.entries())
    assert [isinstance(e, SkippedScan) for e in entries] == [False, True, False]
    skipped = entries[1]
    assert isinstance(skipped, SkippedScan)
    assert skipped.reason == f'CustomMsg point_num is 10 but it holds {POINTS_PER_SCAN} points.'
    assert skipped.stamp_ns == sweeps[1].stamp_ns
    with pytest.raises(InvalidPointCloudError, match=f'message 1 of {TOPIC}: CustomMsg point_num'):
        list(source)


def test_a_custom_msg_cut_short_or_with_bytes_after_its_points_is_refused(
    sweeps: list[Sweep],
) -> None:
    raw = bytes(JAZZY.serialize_cdr(_custom_msg(JAZZY, DRIVER2, sweeps[0]), DRIVER2))
    with pytest.raises(InvalidPointCloudError, match=r'truncated: its 6000 points need \d+'):
        custom_msg_to_array(raw[:-40])
    with pytest.raises(InvalidPointCloudError, match='truncated before its points'):
        custom_msg_to_array(raw[:30])
    with pytest.raises(InvalidPointCloudError, match='40 bytes after its 6000 points'):
        custom_msg_to_array(raw + bytes(40))
    with pytest.raises(InvalidPointCloudError, match="no field 'intensity'"):
        custom_msg_to_array(raw, fields=['intensity'])


def test_offset_times_beyond_a_sweep_leave_the_scan_undeskewed_with_a_warning(
    sweeps: list[Sweep], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bad = [replace(s, offsets=s.offsets * 40) for s in sweeps[:2]]  # up to 4 s: no sweep
    bag = _write_custom_bag(tmp_path / 'slow', bad, 'sqlite3')
    odometry = Odometry(KentRegConfig())
    with caplog.at_level(logging.WARNING, logger='kentreg_ros'):
        for scan in open_scan_source(bag):
            odometry.step(scan.points, scan.stamp_ns, point_times=point_time_field(scan.extras))
    assert len(odometry.poses) == 2
    text = caplog.text
    assert "Not deskewing: the per-point times (field 'offset_time' (uint32, Livox)" in text
    assert 'no sweep of at most 2.0 s' in text


def test_a_custom_msg_of_another_layout_is_refused_not_misread(tmp_path: Path) -> None:
    """The first livox_ros_driver's CustomMsg had a timestep and points without offset_time:
    the definition the bag carries says so, and the bag is refused."""
    from rosbags.typesys import get_types_from_msg

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(
        get_types_from_msg(
            'float32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\nuint8 line\n',
            'livox_ros_driver/msg/CustomPoint',
        )
    )
    store.register(
        get_types_from_msg(
            'std_msgs/Header header\nuint64 timebase\nuint32 timestep\nuint32 point_num\n'
            'uint8 lidar_id\nuint8[3] rsvd\nCustomPoint[] points\n',
            DRIVER1,
        )
    )
    with Writer(tmp_path / 'old', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(TOPIC, DRIVER1, typestore=store)
        types = store.types
        msg = types[DRIVER1](
            header=types['std_msgs/msg/Header'](
                stamp=types['builtin_interfaces/msg/Time'](sec=1, nanosec=0), frame_id='livox'
            ),
            timebase=1_000_000_000,
            timestep=1000,
            point_num=0,
            lidar_id=0,
            rsvd=np.zeros(3, np.uint8),
            points=[],
        )
        writer.write(conn, 1_000_000_000, store.serialize_cdr(msg, DRIVER1))
    with pytest.raises(BagError, match=r"not Livox's driver's: its fields are .*timestep"):
        open_scan_source(tmp_path / 'old')


# --- the player and the node -------------------------------------------------------------------


def test_a_restamped_scan_keeps_its_absolute_times_a_sweep_around_the_stamp(
    sweeps: list[Sweep],
) -> None:
    """What kentreg_play does on a --loop pass or with --restamp now."""
    sweep = sweeps[0]
    later = sweep.stamp_ns + 3_600 * 1_000_000_000 + 123
    for times_s in (False, True):
        extras = pointcloud2_to_array(_driver2_pointcloud2(sweep, times_s=times_s)).extras
        moved = shift_point_times(extras, sweep.stamp_ns, later)
        assert moved['timestamp'].dtype == np.float64 and moved['line'] is extras['line']
        found = sweep_times(moved['timestamp'], later, field='timestamp')
        np.testing.assert_allclose(found.seconds, sweep.offsets * 1e-9, rtol=0, atol=1e-6)
    absolute = {'timestamp': sweep.stamp_ns + sweep.offsets.astype(np.uint64)}
    moved = shift_point_times(absolute, sweep.stamp_ns, later)
    np.testing.assert_array_equal(moved['timestamp'], later + sweep.offsets.astype(np.uint64))
    found = sweep_times(moved['timestamp'], later, field='timestamp')  # integer ns: exact
    np.testing.assert_array_equal(found.seconds, sweep.offsets.astype(np.int64) * 1e-9)
    relative = {'offset_time': sweep.offsets}  # counts from the stamp, wherever it goes
    assert shift_point_times(relative, sweep.stamp_ns, later)['offset_time'] is sweep.offsets


def test_the_live_hint_for_a_custom_msg_points_to_the_pointcloud2_output() -> None:
    for msgtype in CUSTOM_MSG_TYPES:
        hint = live_custom_msg_hint('/livox/lidar', msgtype)
        assert f'/livox/lidar carries {msgtype}' in hint and 'not on PyPI' in hint
        assert 'xfer_format to 0' in hint and 'kentreg_replay BAG --topic /livox/lidar' in hint


@pytest.mark.integration
def test_the_node_says_once_that_its_input_topic_carries_another_type(
    rclpy_context: Any,
) -> None:
    """DDS delivers nothing of another type, silently; the node looks at the publishers (of
    another participant: one context refuses a second type on a topic)."""
    import time

    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from std_msgs.msg import String

    from kentreg_ros.ros.node import KentRegNode

    topic = f'/kentreg_livox_test_{uuid.uuid4().hex[:8]}'
    node = KentRegNode(
        context=rclpy_context,
        node_name=f'kentreg_test_{uuid.uuid4().hex[:8]}',
        cli_args=['--ros-args', '-r', f'points:={topic}'],
    )
    for timer in node.timers:
        timer.cancel()
    context = Context()
    rclpy.init(context=context)
    other = Node(f'livox_stand_in_{uuid.uuid4().hex[:8]}', context=context)
    try:
        other.create_publisher(String, topic, 10)
        said: list[str] = []
        deadline = time.monotonic() + 30.0
        while not said and time.monotonic() < deadline:
            said = node.check_input_type()
            time.sleep(0.1)
        assert said == [
            f'{topic} carries std_msgs/msg/String, not sensor_msgs/msg/PointCloud2: no message '
            'of it reaches this node. Remap points to a PointCloud2 topic.'
        ]
        assert node.check_input_type() == []  # once
    finally:
        other.destroy_node()
        rclpy.try_shutdown(context=context)
        node.destroy_node()
