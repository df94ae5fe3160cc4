"""Bags through rosbags: MCAP, sqlite3 and ROS 1 in; MCAP out; topic choice; damaged bags."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from kentreg_ros.io.bags import bag_topics, is_bag
from kentreg_ros.io.bagwriter import BagWriter
from kentreg_ros.io.errors import BagError, PoseFileError, ScanFileError
from kentreg_ros.io.pointcloud2 import (
    MessageFactory,
    array_to_pointcloud2,
    rosbags_factory,
)
from kentreg_ros.io.recordings import open_recording, read_ground_truth
from kentreg_ros.io.scanfiles import write_pcd
from kentreg_ros.io.sources import open_scan_source

JAZZY = get_typestore(Stores.ROS2_JAZZY)
PC2 = 'sensor_msgs/msg/PointCloud2'
T0 = 1_700_000_000_000_000_000


def _scans(n: int, points: int = 2000, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        pts = rng.normal(scale=8.0, size=(points, 3)).astype(np.float32)
        out.append((pts, rng.integers(0, 255, points).astype(np.float32)))
    return out


def _write_rosbag2(
    path: Path,
    scans: list[tuple[np.ndarray, np.ndarray]],
    *,
    storage: StoragePlugin = StoragePlugin.MCAP,
    topics: tuple[str, ...] = ('/points',),
    extra_topics: tuple[tuple[str, str], ...] = (),
) -> None:
    """A bag written with rosbags' own Writer (not kentreg's BagWriter)."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        conns = [writer.add_connection(t, PC2, typestore=JAZZY) for t in topics]
        for topic, msgtype in extra_topics:
            writer.add_connection(topic, msgtype, typestore=JAZZY)
        for i, (pts, intensity) in enumerate(scans):
            stamp = T0 + i * 100_000_000
            msg = array_to_pointcloud2(
                pts, extra={'intensity': intensity}, frame_id='velodyne', stamp_ns=stamp
            )
            for conn in conns:
                writer.write(conn, stamp + 5, JAZZY.serialize_cdr(msg, PC2))


def _check(source: Any, scans: list[tuple[np.ndarray, np.ndarray]]) -> None:
    got = list(source)
    assert len(got) == len(scans) == len(source)
    for i, ((stamp, frame, pts, extras), (want, intensity)) in enumerate(
        zip(got, scans, strict=True)
    ):
        assert stamp == T0 + i * 100_000_000 and frame == 'velodyne'
        np.testing.assert_array_equal(pts, want)
        np.testing.assert_array_equal(extras['intensity'], intensity)


def test_pointcloud2_through_mcap_gives_identical_points(tmp_path: Path) -> None:
    scans = _scans(3)
    _write_rosbag2(tmp_path / 'bag', scans)
    mcap = tmp_path / 'bag' / 'bag.mcap'
    for path in (tmp_path / 'bag', mcap):  # the rosbag2 folder and the bare file
        assert is_bag(path)
        source = open_scan_source(path)
        assert source.topic == '/points'
        _check(source, scans)


def test_sqlite3_bag_file_and_folder(tmp_path: Path) -> None:
    scans = _scans(2, seed=1)
    _write_rosbag2(tmp_path / 'db', scans, storage=StoragePlugin.SQLITE3)
    _check(open_scan_source(tmp_path / 'db'), scans)
    _check(open_scan_source(tmp_path / 'db' / 'db.db3'), scans)


def test_ros1_bag(tmp_path: Path) -> None:
    noetic = get_typestore(Stores.ROS1_NOETIC)
    types = noetic.types
    factory = MessageFactory(
        point_cloud2=types[PC2],
        point_field=types['sensor_msgs/msg/PointField'],
        header=lambda **kw: types['std_msgs/msg/Header'](seq=0, **kw),
        time=types['builtin_interfaces/msg/Time'],
    )
    scans = _scans(2, seed=2)
    path = tmp_path / 'old.bag'
    with Writer1(path) as writer:
        conn = writer.add_connection('/velodyne_points', PC2, typestore=noetic)
        for i, (pts, intensity) in enumerate(scans):
            stamp = T0 + i * 100_000_000
            msg = array_to_pointcloud2(
                pts,
                extra={'intensity': intensity},
                frame_id='velodyne',
                stamp_ns=stamp,
                factory=factory,
            )
            writer.write(conn, stamp, noetic.serialize_ros1(msg, PC2))
    source = open_scan_source(path)
    assert source.topic == '/velodyne_points'
    _check(source, scans)


def test_topic_choice(tmp_path: Path) -> None:
    scans = _scans(1, points=10)
    _write_rosbag2(
        tmp_path / 'two',
        scans,
        topics=('/front', '/rear'),
        extra_topics=(('/odom', 'nav_msgs/msg/Odometry'),),
    )
    with pytest.raises(
        BagError,
        match=r'2 sensor_msgs/msg/PointCloud2 topics \(/front, /rear\); '
        'choose one with topic=',
    ):
        open_scan_source(tmp_path / 'two')
    assert open_scan_source(tmp_path / 'two', topic='/rear').topic == '/rear'
    with pytest.raises(BagError, match=r"no topic '/points'; PointCloud2 topics: /front, /rear"):
        open_scan_source(tmp_path / 'two', topic='/points')
    with pytest.raises(BagError, match='topic /odom carries nav_msgs/msg/Odometry, not'):
        open_scan_source(tmp_path / 'two', topic='/odom')
    with pytest.raises(BagError, match=r'topic /odom has no messages|no poses'):
        read_ground_truth(tmp_path / 'two', topic='/odom')
    topics = bag_topics(tmp_path / 'two')
    assert {t.name: (t.msgtype, t.count) for t in topics.values()} == {
        '/front': (PC2, 1),
        '/rear': (PC2, 1),
        '/odom': ('nav_msgs/msg/Odometry', 0),
    }


def test_bag_without_clouds_and_empty_topic(tmp_path: Path) -> None:
    _write_rosbag2(
        tmp_path / 'none', [], topics=(), extra_topics=(('/odom', 'nav_msgs/msg/Odometry'),)
    )
    with pytest.raises(BagError, match=r'no sensor_msgs/msg/PointCloud2 topic; topics: /odom'):
        open_scan_source(tmp_path / 'none')
    _write_rosbag2(tmp_path / 'empty', [])
    with pytest.raises(BagError, match='topic /points has no messages'):
        open_scan_source(tmp_path / 'empty')


def test_truncated_mcap_delivers_messages_before_the_cut(tmp_path: Path) -> None:
    scans = _scans(12, points=20000, seed=3)  # 240 kB per message: several MCAP chunks
    _write_rosbag2(tmp_path / 'bag', scans)
    raw = (tmp_path / 'bag' / 'bag.mcap').read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(raw[: len(raw) // 2])
    source = open_scan_source(cut)
    delivered = []
    with pytest.raises(
        BagError,
        match=r'cut.mcap: MCAP file is truncated or corrupt after \d+ '
        r'message\(s\) of /points',
    ):
        for scan in source:
            delivered.append(scan)
    assert 3 <= len(delivered) < 12
    for (_, _, pts, _), (want, _) in zip(delivered, scans[: len(delivered)], strict=True):
        np.testing.assert_array_equal(pts, want)


def test_corrupt_chunk_in_indexed_mcap_raises_after_earlier_messages(tmp_path: Path) -> None:
    scans = _scans(12, points=20000, seed=4)
    with BagWriter(tmp_path / 'bag') as writer:  # zstd chunks
        for i, (pts, intensity) in enumerate(scans):
            writer.write_pointcloud(
                '/points',
                T0 + i * 100_000_000,
                pts,
                extra={'intensity': intensity},
                frame_id='velodyne',
            )
    path = writer.mcap_path
    raw = bytearray(path.read_bytes())
    middle = len(raw) // 2
    raw[middle : middle + 4096] = bytes(4096)
    path.write_bytes(bytes(raw))
    delivered = []
    with pytest.raises(BagError, match=r'bag is corrupt after \d+ message\(s\) of /points'):
        for scan in open_scan_source(tmp_path / 'bag'):
            delivered.append(scan)
    assert 1 <= len(delivered) < 12
    np.testing.assert_array_equal(delivered[0].points, scans[0][0])


def test_not_a_bag(tmp_path: Path) -> None:
    junk = tmp_path / 'junk.mcap'
    junk.write_bytes(b'not an mcap file at all')
    with pytest.raises(BagError, match='junk.mcap'):
        open_scan_source(junk)
    with pytest.raises(BagError, match='neither a bag'):
        open_scan_source(tmp_path / 'nothing.xyz')


def test_bag_writer_writes_every_message_type(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, 3] = rng.normal(size=(3, 3))
    T[1, :3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    stamps = T0 + np.arange(3) * 500_000_000
    cov = np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
    with BagWriter(tmp_path / 'out.mcap', custom_data={'source': 'unit test'}) as writer:
        for i in range(3):
            writer.write_pointcloud('/points', int(stamps[i]), rng.normal(size=(100, 3)))
            writer.write_pose('/ground_truth', int(stamps[i]), T[i])
            writer.write_odometry('/kentreg/odometry', int(stamps[i]), T[i], pose_covariance=cov)
            writer.write_transform(int(stamps[i]), T[i], frame_id='odom', child_frame_id='lidar')
        writer.write_path('/kentreg/path', int(stamps[-1]), stamps, T, frame_id='odom')
        with pytest.raises(BagError, match='already carries'):
            writer.write_pose('/points', 0, T[0])
    assert writer.path == tmp_path / 'out' and writer.mcap_path.is_file()
    assert writer.counts == {
        '/points': 3,
        '/ground_truth': 3,
        '/kentreg/odometry': 3,
        '/tf': 3,
        '/kentreg/path': 1,
    }
    assert 'unit test' in (tmp_path / 'out' / 'metadata.yaml').read_text()
    for topic in ('/ground_truth', '/kentreg/odometry', '/kentreg/path'):
        stamps_back, T_back = read_ground_truth(tmp_path / 'out', topic=topic)
        np.testing.assert_array_equal(stamps_back, stamps)
        np.testing.assert_allclose(T_back, T, atol=1e-12)
    with AnyReader([tmp_path / 'out']) as reader:
        msgs = {c.topic: reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()}
    odom = msgs['/kentreg/odometry']
    assert (odom.header.frame_id, odom.child_frame_id) == ('odom', 'base_link')
    np.testing.assert_array_equal(odom.pose.covariance.reshape(6, 6), cov)
    tf = msgs['/tf'].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ('odom', 'lidar')
    with pytest.raises(BagError, match='exists; not overwriting'):
        BagWriter(tmp_path / 'out').open()
    with BagWriter(tmp_path / 'out', overwrite=True) as writer:
        writer.write_pose('/ground_truth', T0, np.eye(4))
    assert len(read_ground_truth(tmp_path / 'out').T_world_sensor) == 1
    (tmp_path / 'notabag').mkdir()
    (tmp_path / 'notabag' / 'thesis.tex').write_text('')
    with pytest.raises(BagError, match='not a rosbag2 folder; not removing'):
        BagWriter(tmp_path / 'notabag', overwrite=True).open()


def test_scan_folder_source(tmp_path: Path) -> None:
    scans = _scans(3, points=50, seed=6)
    for i, (pts, intensity) in enumerate(scans):
        write_pcd(tmp_path / f'scan{i}.pcd', pts, {'intensity': intensity})
    source = open_scan_source(tmp_path, rate=2.0, start_ns=T0)
    got = list(source)
    assert [s.stamp_ns for s in got] == [T0, T0 + 500_000_000, T0 + 1_000_000_000]
    assert {s.frame_id for s in got} == {'lidar'}
    np.testing.assert_array_equal(got[2].points, scans[2][0])
    pose_file = tmp_path / 'poses.tum'
    pose_file.write_text('10.5 0 0 0 0 0 0 1\n11.0 1 0 0 0 0 0 1\n11.5 2 0 0 0 0 0 1\n')
    timed = open_scan_source(tmp_path, poses=pose_file)
    assert [s.stamp_ns for s in timed] == [10_500_000_000, 11_000_000_000, 11_500_000_000]
    pose_file.write_text('10.5 0 0 0 0 0 0 1\n')
    with pytest.raises(PoseFileError, match='1 poses for 3 scans'):
        open_scan_source(tmp_path, poses=pose_file)
    one = open_scan_source(tmp_path / 'scan1.pcd')
    assert len(one) == 1
    with pytest.raises(ValueError, match='`topic` applies to bags'):
        open_scan_source(tmp_path, topic='/points')


def test_open_recording_finds_the_reference_poses(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    scans = _scans(3, points=50, seed=8)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, 0, 3] = [0.0, 0.5, 1.0]
    stamps = T0 + np.arange(3) * 500_000_000
    bag = tmp_path / 'bag'
    with BagWriter(bag) as writer:
        for i, (pts, _) in enumerate(scans):
            writer.write_pointcloud('/points', int(stamps[i]), pts)
            writer.write_pose('/ground_truth', int(stamps[i]), T[i])
    source, reference, origin = open_recording(bag)
    assert origin == '/ground_truth' and reference is not None
    np.testing.assert_array_equal(reference.stamps_ns, stamps)
    assert [s.stamp_ns for s in source] == stamps.tolist()
    assert all(not s.extras for s in source)  # x, y, z only by default
    with caplog.at_level(logging.INFO, logger='kentreg_ros.io'):
        assert open_recording(bag, poses_topic='/other').reference is None
    assert 'No ground truth from the bag' in caplog.text
    # A scan folder with BALM's alidarPose.csv beside the scans: its times stamp the scans.
    folder = tmp_path / 'scans'
    folder.mkdir()
    lines = []
    for i, (pts, intensity) in enumerate(scans):
        write_pcd(folder / f'full{i}.pcd', pts, {'intensity': intensity})
        lines += [','.join(f'{v:g}' for v in row) + ',' for row in T[i, :3]]
        lines.append(f'0,0,0,{stamps[i] / 1e9:.1f},')
    (folder / 'alidarPose.csv').write_text('\n'.join(lines) + '\n')
    source, reference, origin = open_recording(folder, fields=None)
    assert origin == str(folder / 'alidarPose.csv') and reference is not None
    assert [s.stamp_ns for s in source] == stamps.tolist()
    assert all(list(s.extras) == ['intensity'] for s in source)
    tum = tmp_path / 'gt.tum'
    tum.write_text('1.0 0 0 0 0 0 0 1\n')
    source, reference, origin = open_recording(folder, poses=tum)
    assert origin == str(tum) and reference is not None and len(reference.T_world_sensor) == 1
    with pytest.raises(ScanFileError, match='no_such: no such file or folder'):
        open_recording(tmp_path / 'no_such')
    with pytest.raises(ValueError, match='`topic` applies to bags'):
        open_recording(folder, topic='/points')


def test_rosbags_factory_messages_serialize() -> None:
    msg = array_to_pointcloud2(np.zeros((3, 3)), factory=rosbags_factory(JAZZY))
    assert JAZZY.deserialize_cdr(JAZZY.serialize_cdr(msg, PC2), PC2).width == 3


def test_entries_put_a_skipped_scan_in_place_of_a_malformed_cloud(tmp_path: Path) -> None:
    """entries() keeps going past a PointCloud2 that cannot be decoded, naming it (index,
    stamp, reason) in its place; plain iteration still raises there, naming the message."""
    scans = _scans(4, points=100, seed=9)
    path = tmp_path / 'one_bad'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/points', PC2, typestore=JAZZY)
        for i, (pts, _) in enumerate(scans):
            stamp = T0 + i * 100_000_000
            msg = array_to_pointcloud2(pts, frame_id='velodyne', stamp_ns=stamp)
            if i == 1:
                msg.fields = [f for f in msg.fields if f.name != 'z']
            writer.write(conn, stamp + 5, JAZZY.serialize_cdr(msg, PC2))
    from kentreg_ros.io.sources import Scan, SkippedScan

    source = open_scan_source(path)
    entries = list(source.entries())
    assert [type(e) for e in entries] == [Scan, SkippedScan, Scan, Scan]
    skipped = entries[1]
    assert isinstance(skipped, SkippedScan)
    assert (skipped.index, skipped.stamp_ns) == (1, T0 + 100_000_000)
    assert skipped.reason == "PointCloud2 has no z field; its fields are ['x', 'y']."
    np.testing.assert_array_equal(entries[2].points, scans[2][0])  # type: ignore[union-attr]
    with pytest.raises(Exception, match=r'message 1 of /points: PointCloud2 has no z field'):
        list(source)


def test_entries_of_a_scan_folder_skip_an_unreadable_file(tmp_path: Path) -> None:
    from kentreg_ros.io.sources import SkippedScan

    scans = _scans(3, points=50, seed=10)
    for i, (pts, intensity) in enumerate(scans):
        write_pcd(tmp_path / f'scan{i}.pcd', pts, {'intensity': intensity})
    (tmp_path / 'scan1.pcd').write_bytes(b'# .PCD v0.7\nFIELDS x y z\n')  # cut in its header
    source = open_scan_source(tmp_path, rate=10.0, start_ns=T0)
    entries = list(source.entries())
    skipped = entries[1]
    assert isinstance(skipped, SkippedScan)
    assert (skipped.index, skipped.stamp_ns) == (1, T0 + 100_000_000)
    assert 'scan1.pcd' in skipped.reason and 'DATA' in skipped.reason
    np.testing.assert_array_equal(entries[2].points, scans[2][0])  # type: ignore[union-attr]
    with pytest.raises(ScanFileError, match='scan1.pcd'):
        list(source)
