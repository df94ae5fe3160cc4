"""``kentreg_play``'s command line, its timing and its summary; no rclpy here
(:mod:`kentreg_ros.ros.play` publishes)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass

from kentreg_ros.cli.common import (
    ArgumentParser,
    CliError,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)

PROG = 'kentreg_play'
#: ``--clock`` without a value publishes at this rate (as ``ros2 bag play --clock`` does).
DEFAULT_CLOCK_HZ = 40.0


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_play`` (ROS arguments are removed first)."""
    parser = ArgumentParser(
        prog=PROG,
        description='Publish the PointCloud2 messages of a bag (or the scans of a folder) on a '
        'ROS 2 topic at the recorded rate, scaled, or fixed. ROS arguments go after '
        '--ros-args (e.g. --ros-args -r points:=/velodyne_points).',
    )
    parser.add_argument(
        'input',
        metavar='BAG_OR_FOLDER',
        help='rosbag2 folder or .mcap/.db3/.bag file, or a folder of scan files '
        '(.pcd, .ply, .bin, .csv; stamped at 10 Hz)',
    )
    parser.add_argument(
        '--topic', default='points', help='topic to publish on (default: points, relative)'
    )
    parser.add_argument(
        '--bag-topic', help='PointCloud2 topic to read from the bag, when it has several'
    )
    parser.add_argument(
        '--rate',
        type=non_negative_float,
        default=None,
        help='playback speed as a multiple of the recorded rate (default 1; 0: as fast as '
        'possible)',
    )
    parser.add_argument(
        '--hz',
        type=positive_float,
        help='publish at this fixed rate instead, whatever the recorded stamps',
    )
    parser.add_argument('--loop', action='store_true', help='repeat until interrupted')
    parser.add_argument(
        '--start', type=non_negative_int, default=0, help='skip this many scans (default 0)'
    )
    parser.add_argument(
        '--max-scans', type=positive_int, help='publish at most this many scans per pass'
    )
    parser.add_argument(
        '--restamp',
        choices=('bag', 'now'),
        default='bag',
        help='header stamps: the recorded ones (bag, default; shifted per --loop pass) or the '
        'time of publishing (now)',
    )
    parser.add_argument(
        '--clock',
        type=positive_float,
        nargs='?',
        const=DEFAULT_CLOCK_HZ,
        metavar='HZ',
        help='also publish the recorded time on /clock (rosgraph_msgs/Clock) for nodes with '
        f'use_sim_time:=true, at HZ (default {DEFAULT_CLOCK_HZ:g}) and before every scan; '
        'needs --restamp bag',
    )
    parser.add_argument(
        '--reliability',
        choices=('reliable', 'best_effort'),
        default='reliable',
        help='QoS reliability of the publisher (default reliable: matches reliable and '
        'best-effort subscribers)',
    )
    parser.add_argument(
        '--depth', type=positive_int, default=10, help='QoS history depth (default 10)'
    )
    parser.add_argument(
        '--wait-subscribers',
        type=non_negative_float,
        default=0.0,
        metavar='SECONDS',
        help='wait up to SECONDS for a subscriber before the first scan (default 0: do not '
        'wait); playback starts anyway when none appears',
    )
    parser.add_argument(
        '--frame-id', help="header frame of the clouds (default: the source's, e.g. lidar)"
    )
    parser.add_argument(
        '--fields',
        default='all',
        help="point fields besides x, y, z: 'all' (default), 'none', or a comma-separated list "
        '(e.g. intensity)',
    )
    parser.add_argument('-q', '--quiet', action='store_true', help='print only errors')
    return parser


@dataclass(frozen=True)
class Timing:
    """When to publish: ``rate`` × recorded rate, or fixed ``hz``; both None: no waiting."""

    rate: float | None
    hz: float | None

    @classmethod
    def from_options(cls, rate: float | None, hz: float | None) -> Timing:
        """``--rate``/``--hz`` as given (None: not given); they exclude each other."""
        if hz is not None and rate is not None:
            raise CliError('--rate and --hz exclude each other; give one')
        if hz is not None:
            return cls(None, hz)
        rate = 1.0 if rate is None else rate
        return cls(rate if rate > 0.0 else None, None)

    def gap_s(self, previous_stamp_ns: int, stamp_ns: int) -> float:
        """Wall-clock seconds between publishing two consecutive scans.

        Recorded stamps that go backwards give 0 (the scan goes out at once).
        """
        if self.hz is not None:
            return 1.0 / self.hz
        if self.rate is None:
            return 0.0
        return max(stamp_ns - previous_stamp_ns, 0) * 1e-9 / self.rate

    def describe(self) -> str:
        """Human-readable, for the log."""
        if self.hz is not None:
            return f'at {self.hz:g} Hz'
        if self.rate is None:
            return 'as fast as possible'
        return f'at {self.rate:g}x the recorded rate'


def fields_option(text: str) -> Sequence[str] | None:
    value = text.strip()
    if value == 'all':
        return None
    if value == 'none':
        return ()
    names = [n.strip() for n in value.split(',') if n.strip()]
    if not names:
        raise CliError(f"--fields: expected 'all', 'none' or field names, got {text!r}")
    return names


@dataclass
class PlaySummary:
    """What a run published."""

    published: int = 0
    points: int = 0
    passes: int = 0
    first_publish_s: float | None = None
    last_publish_s: float | None = None
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    subscribers_at_start: int = 0
    #: Scans that could not be decoded (a malformed PointCloud2): skipped, said and counted.
    skipped: int = 0

    @property
    def duration_s(self) -> float:
        """Wall time from the first to the last publication."""
        if self.first_publish_s is None or self.last_publish_s is None:
            return 0.0
        return self.last_publish_s - self.first_publish_s

    @property
    def rate_hz(self) -> float | None:
        """Measured publishing rate (None with fewer than two messages)."""
        if self.published < 2 or self.duration_s <= 0.0:
            return None
        return (self.published - 1) / self.duration_s

    def format(self, topic: str) -> str:
        """One line for the terminal."""
        hz = self.rate_hz
        rate = f'{hz:.2f} Hz' if hz is not None else 'one message'
        mean = self.points / self.published if self.published else 0.0
        skipped = f'; {self.skipped} skipped (could not be decoded)' if self.skipped else ''
        return (
            f'{PROG}: published {self.published} scan(s) on {topic} in {self.duration_s:.2f} s '
            f'({rate}; {mean:.0f} points per scan; {self.passes} pass(es){skipped})'
        )
