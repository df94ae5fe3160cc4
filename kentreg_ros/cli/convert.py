"""``kentreg_convert``: scan files (+ pose file) or a bag -> rosbag2 MCAP with /points and
/ground_truth.

Examples
--------
A folder of scans with BALM poses (header stamps from the pose times)::

    kentreg_convert ../shared/data/balm --poses ../shared/data/balm/alidarPose.csv \\
        --voxel-size 0.1 --fields intensity -o bags/balm_50

Two scan files in a chosen order, stamped at 1 Hz::

    kentreg_convert target.ply source.ply --rate 1 -o pair

Output: a rosbag2 folder (``<out>/<name>.mcap`` + ``metadata.yaml``) with ``/points``
(sensor_msgs/PointCloud2, float32 x y z + kept fields, frame ``lidar``) and, with ``--poses``,
``/ground_truth`` (geometry_msgs/PoseStamped of the sensor in frame ``world``, same stamps).
"""

from __future__ import annotations

import argparse
import logging
import shlex
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kentreg_ros import __version__
from kentreg_ros.cli import common
from kentreg_ros.core import KentRegError, voxel_downsample
from kentreg_ros.io.recordings import GROUND_TRUTH_TOPIC

logger = logging.getLogger('kentreg_ros.cli.convert')

PROG = 'kentreg_convert'


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_convert``."""
    parser = common.ArgumentParser(
        prog=PROG,
        description='Turn a scan folder (PCD, PLY, KITTI .bin, ETH CSV) or a bag into a rosbag2 '
        'MCAP with /points (PointCloud2) and /ground_truth (PoseStamped).',
    )
    add = parser.add_argument
    add(
        'inputs',
        nargs='+',
        type=Path,
        metavar='INPUT',
        help='a scan folder (natural order: full0, full1, ..., full10), a bag, or scan files '
        'in the order to write them',
    )
    add(
        '-o',
        '--output',
        type=Path,
        required=True,
        help='rosbag2 folder to create (OUT/OUT.mcap + metadata.yaml)',
    )
    add(
        '--poses',
        type=Path,
        help='pose file: KITTI, TUM, ETH pose_scanner_leica.csv or BALM '
        'alidarPose.csv; one pose per scan',
    )
    add(
        '--pose-format',
        choices=['auto', 'kitti', 'tum', 'eth', 'balm'],
        default='auto',
        help='pose file format (default: detect)',
    )
    add('--times', type=Path, help='KITTI times.txt for KITTI poses')
    add(
        '--rate',
        type=common.positive_float,
        help='stamp scans at this rate in Hz (default: the pose file times, '
        'or 10 Hz without them)',
    )
    add(
        '--start-time',
        type=common.non_negative_float,
        default=0.0,
        help='first stamp in seconds when stamping by rate (default 0)',
    )
    add('--topic', help='PointCloud2 topic of an input bag with several')
    add(
        '--voxel-size',
        type=common.non_negative_float,
        default=0.0,
        help='voxel downsample to this size in metres (centroids; fields '
        'from the nearest original point); 0 keeps every point',
    )
    add(
        '--fields',
        default=None,
        help="comma-separated extra fields to keep (default all, 'none' for x y z only)",
    )
    add('--frame-id', default='lidar', help='sensor frame (default lidar)')
    add('--world-frame', default='world', help='ground truth frame')
    add('--points-topic', default='/points')
    add('--gt-topic', default=GROUND_TRUTH_TOPIC)
    add('--no-compress', action='store_true', help='write uncompressed MCAP chunks (default zstd)')
    add(
        '--overwrite',
        action='store_true',
        help='replace OUTPUT if it is an existing rosbag2 folder',
    )
    add('-q', '--quiet', action='store_true', help='no progress bar or summary')
    add('--version', action='version', version=f'%(prog)s {__version__}')
    return parser


def _field_list(text: str | None) -> list[str] | None:
    if text is None:
        return None
    if text.strip().lower() in ('', 'none'):
        return []
    return [f.strip() for f in text.split(',') if f.strip()]


def downsample_scan(
    points: NDArray[np.floating[Any]],
    extras: dict[str, NDArray[Any]],
    voxel_size: float,
) -> tuple[NDArray[np.float64], dict[str, NDArray[Any]]]:
    """Voxel centroids of ``points``, each with the extra fields of its nearest original point.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
    extras : dict of str to ndarray, each shape (N,) or (N, k)
    voxel_size : float
        Voxel edge in metres (> 0).

    Returns
    -------
    points : ndarray, shape (M, 3)
    extras : dict of str to ndarray, each shape (M,) or (M, k)
        Nearest-point values keep integer fields (ring, per-point time) meaningful, where an
        average would not.
    """
    centroids = voxel_downsample(points, voxel_size)
    if not extras:
        return centroids, {}
    if not len(centroids):
        return centroids, {name: values[:0] for name, values in extras.items()}
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(points).query(centroids, k=1)
    return centroids, {name: values[nearest] for name, values in extras.items()}


def _open_source(args: argparse.Namespace, fields: list[str] | None) -> Any:
    from kentreg_ros.io.bags import is_bag
    from kentreg_ros.io.poses import read_poses
    from kentreg_ros.io.scanfiles import SCAN_SUFFIXES
    from kentreg_ros.io.sources import FilesScanSource, open_scan_source

    start_ns = round(args.start_time * 1e9)
    poses = None
    if args.poses is not None:
        fmt = None if args.pose_format == 'auto' else args.pose_format
        poses = read_poses(args.poses, format=fmt, times=args.times)
    if len(args.inputs) == 1:
        (path,) = args.inputs
        if is_bag(path):
            if args.rate is not None:
                raise ValueError('--rate applies to scan files; a bag keeps its header stamps.')
            return open_scan_source(path, topic=args.topic, fields=fields), poses
        if args.topic is not None:
            raise ValueError(f'--topic applies to bags; {path} is not a bag.')
        if path.is_dir() and poses is None:
            for name in ('alidarPose.csv', 'pose_scanner_leica.csv', 'poses.txt'):
                if (path / name).is_file():
                    logger.info(
                        '%s is there; pass --poses %s to write /ground_truth.',
                        path / name,
                        path / name,
                    )
        source = open_scan_source(
            path,
            fields=fields,
            poses=poses,
            rate=args.rate,
            start_ns=start_ns,
            frame_id=args.frame_id,
        )
        return source, poses
    bad = [p for p in args.inputs if not (p.is_file() and p.suffix.lower() in SCAN_SUFFIXES)]
    if bad:
        raise ValueError(
            f'{bad[0]}: with several inputs each must be a scan file ({", ".join(SCAN_SUFFIXES)}).'
        )
    source = FilesScanSource(
        args.inputs,
        poses=poses,
        rate=args.rate,
        start_ns=start_ns,
        frame_id=args.frame_id,
        fields=fields,
    )
    return source, poses


def _write_scans(
    args: argparse.Namespace, source: Any, poses: Any, writer: Any, progress: dict[str, Any]
) -> None:
    with common.progress_bar(PROG, len(source), enabled=not args.quiet, terminal_only=True) as bar:
        for index, (stamp_ns, _frame, points, extras) in enumerate(source):
            if args.voxel_size > 0.0:
                points, extras = downsample_scan(points, extras, args.voxel_size)
            writer.write_pointcloud(
                args.points_topic, stamp_ns, points, extra=extras, frame_id=args.frame_id
            )
            if poses is not None:
                writer.write_pose(
                    args.gt_topic, stamp_ns, poses.T_world_sensor[index], frame_id=args.world_frame
                )
            progress['scans'] = index + 1
            progress['points'] += len(points)
            if bar is not None:
                bar.update()


def _convert(args: argparse.Namespace, progress: dict[str, Any]) -> None:
    from kentreg_ros.io.bagwriter import BagWriter
    from kentreg_ros.io.errors import PoseFileError

    fields = _field_list(args.fields)
    source, poses = _open_source(args, fields)
    if poses is not None and len(poses.T_world_sensor) != len(source):
        raise PoseFileError(
            f'{args.poses}: {len(poses.T_world_sensor)} poses for '
            f'{len(source)} scans; give one pose per scan.'
        )
    logger.info('Reading %s.', source.description)
    custom = {
        'kentreg_convert.version': __version__,
        'kentreg_convert.command': shlex.join([PROG, *progress.get('argv', [])]),
    }
    progress['points'] = 0
    writer = BagWriter(
        args.output, compress=not args.no_compress, overwrite=args.overwrite, custom_data=custom
    )
    writer.open()
    progress['output'] = 1
    try:
        _write_scans(args, source, poses, writer, progress)
    except BaseException:
        writer.close()  # what was written stays a valid bag
        if not progress.get('scans'):
            shutil.rmtree(writer.path, ignore_errors=True)  # nothing useful: leave no folder
            progress['output'] = 0
        raise
    writer.close()
    n = progress.get('scans', 0)
    size = sum(f.stat().st_size for f in writer.path.iterdir())
    logger.info(
        'Wrote %d scans (%.0f points each on average, %d non-finite dropped)%s to %s (%.1f MB).',
        n,
        progress['points'] / max(n, 1),
        source.n_dropped,
        f' and {n} poses' if poses is not None else '',
        writer.path,
        size / 1e6,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_convert``; returns the exit status (0, 2 on bad input, 130)."""
    return common.run_main(PROG, lambda: _main(argv))


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    if args.times is not None and args.poses is None:
        raise common.CliError('--times needs --poses (a KITTI pose file)')
    level = logging.WARNING if args.quiet else logging.INFO
    progress: dict[str, Any] = {'argv': list(sys.argv[1:] if argv is None else argv)}
    with common.logging_to_stderr(PROG, level, info_level=False):
        try:
            _convert(args, progress)
        except (common.CliError, KentRegError, OSError, ValueError) as exc:
            if not progress.get('output'):
                raise
            raise common.CliError(
                f'{common.one_line(exc)} ({progress.get("scans", 0)} scan(s) written to '
                f'{args.output} before this)'
            ) from exc
    return common.EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
