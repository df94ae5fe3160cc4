"""Recordings the tests write: bags made from the real sample with rosbags' own Writer."""

from __future__ import annotations

from pathlib import Path


def bag_with_malformed_clouds(sample_bag: Path, path: Path, n: int, bad: set[int]) -> list[int]:
    """Write, with rosbags' own Writer, the first ``n`` scans of the sample bag (its raw CDR
    messages) and its ground truth; the scans at ``bad`` with 7 bytes cut off their data (a
    PointCloud2 that cannot be decoded). Returns the header stamps of the ``n`` scans."""
    import dataclasses

    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    stamps: list[int] = []
    with (
        AnyReader([sample_bag]) as reader,
        Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer,
    ):
        out = {
            c.topic: writer.add_connection(c.topic, c.msgtype, typestore=store)
            for c in reader.connections
        }
        for connection, log_time, raw in reader.messages():
            if connection.topic == '/points':
                if len(stamps) == n:
                    continue
                msg = reader.deserialize(raw, connection.msgtype)
                stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
                if len(stamps) - 1 in bad:
                    msg = dataclasses.replace(msg, data=msg.data[:-7])
                    raw = store.serialize_cdr(msg, connection.msgtype)
            writer.write(out[connection.topic], log_time, raw)
    return stamps
