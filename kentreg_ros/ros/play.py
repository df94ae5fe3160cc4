"""``kentreg_play``: publish the point clouds of a bag or a scan folder on a ROS 2 topic.

A stand-in for ``ros2 bag play`` where ros2cli is not installed (pip-only ROS 2): it feeds
``kentreg_node`` (or anything else) with the scans of a bag (a PointCloud2 or Livox
``CustomMsg`` topic, published as PointCloud2), or with the scans of a folder of
``.pcd``/``.ply``/``.bin``/``.csv`` files, through rclpy.

Examples
--------
Feed the sample recording to a node subscribed to ``points``, at the recorded rate (2 Hz)::

    kentreg_play bags/balm_50

Four times faster, repeating, on another topic, waiting up to 10 s for a subscriber::

    kentreg_play bags/balm_50 --rate 4 --loop --topic /velodyne_points --wait-subscribers 10

Simulated time for nodes started with ``use_sim_time:=true``::

    kentreg_play bags/balm_50 --clock

Messages are decoded and re-encoded (:func:`~kentreg_ros.io.pointcloud2.array_to_pointcloud2`):
x, y, z as float32 plus the other fields of the source (``--fields``), non-finite points
dropped, organised clouds flattened into one row, as :func:`~kentreg_ros.io.open_scan_source`
reads them. The topic ``--topic`` is relative by default (``points``), so it follows the
namespace and ``--ros-args -r points:=...`` remapping.

Timing: each scan is published when its stamp, relative to the first one, divided by
``--rate``, has elapsed; a late scan goes out at once and the schedule continues from it (none
is skipped, no gap is compressed to catch up); the time publishing takes does not delay the
schedule. ``--rate 0`` publishes as fast as possible and ``--hz`` at a fixed rate. ``--loop``
repeats; with ``--restamp bag`` (default) every pass is shifted by the span of the previous one
plus one scan period, so the stamps keep increasing. ``--restamp now`` stamps each message with
the current time instead. Absolute per-point times (a Hesai/Robosense or livox_ros_driver2
``timestamp``) move with the stamp, so re-stamped scans are deskewed like the recorded ones.

A scan that cannot be decoded (a malformed PointCloud2) is skipped, said on stderr (the first
few) and counted in the summary, as ``kentreg_node`` and ``kentreg_replay`` do; the rest of
the input is published.

Exit status: 0 when every scan that could be decoded was published, 2 on bad input (one line on
stderr, including a bag that turns out to be damaged after some scans were published, and an
input of which no scan could be decoded), 130 when interrupted (Ctrl-C, SIGTERM, or an
external ROS shutdown).
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kentreg_ros.cli.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    CliError,
    interrupt_through_rclpy,
    logging_to_stderr,
    run_main,
)
from kentreg_ros.ros.playopts import PROG, PlaySummary, Timing, build_parser, fields_option

if TYPE_CHECKING:
    from kentreg_ros.io.sources import SkippedScan

__all__ = ['PROG', 'Player', 'PlaySummary', 'Timing', 'build_parser', 'main']

logger = logging.getLogger('kentreg_ros.ros.play')  # also when run as __main__

NODE_NAME = 'kentreg_play'
#: Gap between two passes of ``--loop`` when the source has a single scan (s, bag time).
SINGLE_SCAN_PERIOD_S = 0.1
#: Longest single sleep while waiting, so shutdown is noticed promptly (s).
MAX_SLEEP_S = 0.05
#: How long the end of a reliable run waits for subscribers to acknowledge the last messages.
ACK_TIMEOUT_S = 5.0
#: Scans that cannot be decoded that are each said on stderr; the rest are only counted (as
#: many as the replay names: enough to see a pattern, few enough not to flood the terminal).
MAX_SKIPPED_SAID = 5


def _ros() -> Any:
    """Import rclpy and the message packages, or raise CliError naming what to install."""
    try:
        import rclpy
        import rclpy.executors
        import rclpy.qos
        import rclpy.utilities
        from builtin_interfaces.msg import Time
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import PointCloud2, PointField
        from std_msgs.msg import Header

        from kentreg_ros.ros import messages
    except ImportError as exc:
        raise CliError(
            f'{PROG} needs rclpy and the ROS 2 message packages ({exc.name} is missing): '
            "source a ROS 2 Jazzy installation or pip install -e '.[ros]'"
        ) from exc
    import types

    return types.SimpleNamespace(
        rclpy=rclpy,
        ExternalShutdownException=rclpy.executors.ExternalShutdownException,
        qos=rclpy.qos,
        remove_ros_args=rclpy.utilities.remove_ros_args,
        Time=Time,
        Clock=Clock,
        PointCloud2=PointCloud2,
        PointField=PointField,
        Header=Header,
        messages=messages,
    )


class Player:
    """Publishes the scans of a source with one rclpy node (no executor needed).

    Parameters
    ----------
    node : rclpy.node.Node
        The node that owns the publishers.
    source : kentreg_ros.io.ScanSource
        Scans to publish.
    options : argparse.Namespace
        Parsed ``kentreg_play`` options.
    ros : namespace
        What :func:`_ros` returns.
    """

    def __init__(self, node: Any, source: Any, options: argparse.Namespace, ros: Any) -> None:
        from kentreg_ros.io.pointcloud2 import rclpy_factory

        self.node = node
        self.source = source
        self.options = options
        self.ros = ros
        self.timing = Timing.from_options(options.rate, options.hz)
        self.factory = rclpy_factory(ros.PointCloud2, ros.PointField, ros.Header, ros.Time)
        qos = ros.qos
        reliability = (
            qos.ReliabilityPolicy.RELIABLE
            if options.reliability == 'reliable'
            else qos.ReliabilityPolicy.BEST_EFFORT
        )
        profile = qos.QoSProfile(
            history=qos.HistoryPolicy.KEEP_LAST,
            depth=options.depth,
            reliability=reliability,
            durability=qos.DurabilityPolicy.VOLATILE,
        )
        self.publisher = node.create_publisher(ros.PointCloud2, options.topic, profile)
        #: Resolved name of the PointCloud2 topic (after namespace and remapping).
        self.topic = str(self.publisher.topic_name)
        self.clock_publisher = (
            node.create_publisher(ros.Clock, '/clock', qos.QoSProfile(depth=1))
            if options.clock is not None
            else None
        )
        self.summary = PlaySummary()

    def _check_ok(self) -> None:
        if not self.node.context.ok():
            raise self.ros.ExternalShutdownException()

    def _publish_clock(self, stamp_ns: int) -> None:
        if self.clock_publisher is None:
            return
        msg = self.ros.Clock()
        msg.clock = self.ros.messages.stamp_to_msg(stamp_ns)
        self.clock_publisher.publish(msg)

    def wait_for_subscribers(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for a subscription on the topic; return the count."""
        deadline = time.monotonic() + timeout_s
        count = int(self.publisher.get_subscription_count())
        while count == 0 and time.monotonic() < deadline:
            self._check_ok()
            time.sleep(MAX_SLEEP_S)
            count = int(self.publisher.get_subscription_count())
        if count == 0 and timeout_s > 0.0:
            logger.warning(
                'No subscriber on %s after %.1f s; publishing anyway.', self.topic, timeout_s
            )
        return count

    def _wait_until(
        self, due_s: float, clock_from: tuple[float, int] | None, stamp_ns: int
    ) -> None:
        """Sleep until ``due_s`` (monotonic), ticking /clock between the two stamps."""
        clock_period = 1.0 / self.options.clock if self.options.clock is not None else None
        next_tick = time.monotonic()
        while True:
            self._check_ok()
            now = time.monotonic()
            if now >= due_s:
                return
            if clock_period is not None and clock_from is not None and now >= next_tick:
                start_s, start_ns = clock_from
                span = due_s - start_s
                fraction = (now - start_s) / span if span > 0.0 else 1.0
                fraction = min(max(fraction, 0.0), 1.0)
                self._publish_clock(start_ns + int(round(fraction * (stamp_ns - start_ns))))
                next_tick = now + clock_period
            wake = due_s if clock_period is None else min(due_s, next_tick)
            time.sleep(max(min(wake - now, MAX_SLEEP_S), 0.0))

    def _scans(self) -> Iterator[tuple[int, Any]]:
        """Yield ``(output_stamp_ns, scan)`` over every pass, stamps shifted per pass."""
        from kentreg_ros.io.sources import ScanSource, SkippedScan

        offset_ns = 0
        n_pass = 0
        while True:
            first_ns: int | None = None
            last_out_ns: int | None = None
            period_ns = 0
            stop = (
                None
                if self.options.max_scans is None
                else (self.options.start + self.options.max_scans)
            )
            n_in_pass = 0
            first_skipped: SkippedScan | None = None
            # A ScanSource says which scans it cannot decode; any other iterable of scans is
            # taken as it is.
            source = self.source
            entries = source.entries() if isinstance(source, ScanSource) else iter(source)
            for index, scan in enumerate(
                itertools.islice(entries, self.options.start, stop), start=self.options.start
            ):
                if isinstance(scan, SkippedScan):
                    first_skipped = first_skipped or scan
                    self._skip(index, scan)
                    continue
                if first_ns is None:
                    first_ns = scan.stamp_ns
                out_ns = int(scan.stamp_ns) + offset_ns
                if last_out_ns is not None and out_ns > last_out_ns:
                    period_ns = out_ns - last_out_ns
                last_out_ns = out_ns
                n_in_pass += 1
                yield out_ns, scan
            if n_in_pass == 0:
                why = f'after --start {self.options.start}'
                if first_skipped is not None:
                    why = (
                        f'{why}: none could be decoded; the first: scan {first_skipped.index}: '
                        f'{first_skipped.reason}'
                    )
                raise CliError(f'{self.options.input}: no scan to publish {why}')
            n_pass += 1
            self.summary.passes = n_pass
            if not self.options.loop or first_ns is None or last_out_ns is None:
                return
            if period_ns == 0:
                period_ns = int(SINGLE_SCAN_PERIOD_S * 1e9)
            # The next pass starts one period after this one ended, in the same timeline.
            offset_ns = last_out_ns + period_ns - first_ns

    def _skip(self, index: int, skipped: SkippedScan) -> None:
        """Count a scan that cannot be decoded; say so for the first few of them."""
        self.summary.skipped += 1
        if self.summary.skipped <= MAX_SKIPPED_SAID:
            stamp = f' (stamp {skipped.stamp_ns * 1e-9:.3f} s)' if skipped.stamp_ns else ''
            logger.warning('Skipped scan %d%s: %s', index, stamp, skipped.reason)
        if self.summary.skipped == MAX_SKIPPED_SAID:
            logger.warning('Further scans that cannot be decoded are only counted.')

    def run(self) -> PlaySummary:
        """Publish every scan on schedule; return what was published.

        Raises
        ------
        rclpy.executors.ExternalShutdownException
            The ROS context was shut down (Ctrl-C, SIGTERM).
        BagError, KentRegError
            The source failed part-way (the summary so far stays in :attr:`summary`).
        """
        opts = self.options
        summary = self.summary
        summary.subscribers_at_start = self.wait_for_subscribers(opts.wait_subscribers)
        frame_override = opts.frame_id
        due_s: float | None = None
        previous: tuple[float, int] | None = None
        previous_stamp_ns: int | None = None
        for stamp_ns, scan in self._scans():
            # Re-stamped with the time of publishing, the message is built then (absolute
            # per-point times move with the stamp).
            msg = (
                None if opts.restamp == 'now' else self.ros_message(scan, stamp_ns, frame_override)
            )
            if due_s is None or previous_stamp_ns is None:
                due_s = time.monotonic()
            else:
                due_s += self.timing.gap_s(previous_stamp_ns, stamp_ns)
                self._wait_until(due_s, previous, stamp_ns)
            self._check_ok()
            sent = time.monotonic()
            if msg is None:
                now_ns = int(self.node.get_clock().now().nanoseconds)
                msg = self.ros_message(scan, now_ns, frame_override)
            else:
                self._publish_clock(stamp_ns)
            self.publisher.publish(msg)
            summary.published += 1
            summary.points += len(scan.points)
            if summary.first_publish_s is None:
                summary.first_publish_s = sent
                summary.first_stamp_ns = stamp_ns
            summary.last_publish_s = sent
            summary.last_stamp_ns = stamp_ns
            # A late scan resets the schedule: the next gap is measured from when it went out,
            # never compressed to catch up. A scan on time keeps it (the time publishing takes
            # does not delay the next one).
            due_s = max(due_s, sent)
            previous = (due_s, stamp_ns)
            previous_stamp_ns = stamp_ns
        return summary

    def ros_message(self, scan: Any, stamp_ns: int, frame_id: str | None) -> Any:
        """An rclpy PointCloud2 of ``scan`` (x, y, z float32 and its extra fields) stamped
        ``stamp_ns``; an absolute per-point time field moves with the stamp
        (:func:`~kentreg_ros.io.pointtimes.shift_point_times`), so the scans of a loop's later
        passes, or re-stamped ones, are deskewed as the first pass is."""
        from kentreg_ros.io.pointcloud2 import array_to_pointcloud2
        from kentreg_ros.io.pointtimes import shift_point_times

        return array_to_pointcloud2(
            scan.points,
            extra=shift_point_times(scan.extras, int(scan.stamp_ns), stamp_ns),
            frame_id=frame_id if frame_id is not None else (scan.frame_id or 'lidar'),
            stamp_ns=stamp_ns,
            factory=self.factory,
        )

    def flush(self, timeout_s: float = ACK_TIMEOUT_S) -> bool:
        """Wait until reliable subscribers acknowledged every message (or ``timeout_s``)."""
        from rclpy.duration import Duration

        if self.options.reliability != 'reliable' or self.summary.published == 0:
            return True
        return bool(self.publisher.wait_for_all_acked(Duration(seconds=timeout_s)))


def _open_source(options: argparse.Namespace) -> Any:
    import numpy as np

    from kentreg_ros.io import open_scan_source

    if not Path(options.input).exists():
        raise CliError(f'{options.input}: no such file or folder')
    source = open_scan_source(
        options.input,
        topic=options.bag_topic,
        fields=fields_option(options.fields),
        dtype=np.float32,
    )
    if options.start >= len(source):
        raise CliError(f'--start {options.start} is past the last scan ({source.description})')
    return source


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_play``; returns the exit status (see the module docstring).

    Parameters
    ----------
    args : sequence of str, optional
        Command-line arguments without the program name (default ``sys.argv[1:]``); ROS
        arguments follow ``--ros-args``.
    """
    argv = list(sys.argv[1:] if args is None else args)
    return run_main(PROG, lambda: _main(argv), interrupted='interrupted before publishing')


def _main(argv: list[str]) -> int:
    ros = _ros()
    options = build_parser().parse_args(ros.remove_ros_args([PROG, *argv])[1:])
    with logging_to_stderr(
        PROG, logging.WARNING if options.quiet else logging.INFO, info_level=False
    ):
        Timing.from_options(options.rate, options.hz)
        if options.clock is not None and options.restamp != 'bag':
            raise CliError('--clock publishes the recorded time; use it with --restamp bag')
        source = _open_source(options)
        return _play(ros, source, options, argv)


def _play(ros: Any, source: Any, options: argparse.Namespace, argv: list[str]) -> int:
    """Publish ``source``; return :data:`EXIT_OK` or :data:`EXIT_INTERRUPTED`.

    Bad input found while playing (a damaged bag, no scan after ``--start``) propagates to
    :func:`~kentreg_ros.cli.common.run_main` once the node is destroyed and the summary of
    what was published is printed.
    """
    rclpy = ros.rclpy
    interrupt_through_rclpy()
    rclpy.init(args=[PROG, *argv])
    node = None
    player: Player | None = None
    status = EXIT_OK
    try:
        node = rclpy.create_node(NODE_NAME)
        player = Player(node, source, options, ros)
        logger.info(
            'Publishing %s on %s (%s, depth %d) %s%s.',
            source.description,
            player.topic,
            options.reliability,
            options.depth,
            player.timing.describe(),
            ', looping' if options.loop else '',
        )
        player.run()
        if not player.flush():
            logger.warning('Not every subscriber acknowledged the last messages in time.')
    except (KeyboardInterrupt, ros.ExternalShutdownException):
        status = EXIT_INTERRUPTED
    except RuntimeError:
        # rclpy's signal handler shuts the context down from another thread (SIGTERM raises no
        # KeyboardInterrupt): an rclpy call already under way then fails with RCLError, a
        # RuntimeError, instead of ExternalShutdownException (ros2/rclpy#398).
        if rclpy.ok():
            raise
        status = EXIT_INTERRUPTED
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        if player is not None and not options.quiet:
            print(player.summary.format(player.topic))
    if status == EXIT_INTERRUPTED:
        published = player.summary.published if player is not None else 0
        print(f'{PROG}: interrupted after {published} scan(s)', file=sys.stderr)
    return status


if __name__ == '__main__':
    sys.exit(main())
