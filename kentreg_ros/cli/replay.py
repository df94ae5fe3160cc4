"""``kentreg_replay``: offline odometry over a bag or a scan folder, with evaluation and a plot.

Every scan is processed, in order, at CPU speed (none is dropped), by the same
:class:`~kentreg_ros.core.odometry.Odometry` the ROS node runs. Then the run is written out and,
when ground truth is known, evaluated. ``--stride N`` processes only every N-th scan (``start,
start + N, ...``), keeping their stamps: a frame-skipping stress test in which the odometry sees
N times the gaps and the evaluation joins consecutive *processed* scans.

Examples
--------
The sample recording (BALM, 50 real scans with reference poses on ``/ground_truth``)::

    kentreg_replay bags/balm_50

A scan folder with its pose file found beside the scans, the paper's recipe, 10 scans::

    kentreg_replay ../shared/data/balm --set mode=paper --max-scans 10

Against a local map instead of the previous scan, writing the map for a viewer::

    kentreg_replay bags/balm_50 --set odometry.model=local_map --map map.ply

Every third scan of the sample (scans 0, 3, 6, ...; three times the motion per pair)::

    kentreg_replay bags/balm_50 --stride 3

Outputs in ``--out`` (default ``results/<timestamp>/``, with ``results/latest`` pointing there)
-------------------------------------------------------------------------------------------------
``odometry.mcap``
    One MCAP file (``ros2 bag play``, Foxglove) with the topics and frames ``kentreg_node``
    publishes (:mod:`kentreg_ros.io.names`), so a recorded run and a live one look alike: per
    scan a nav_msgs/Odometry on ``/kentreg/odometry``, a geometry_msgs/PoseStamped on
    ``/kentreg/pose``, a tf2_msgs/TFMessage on ``/tf`` (``odom`` -> the scans' frame, the
    node's child frame when ``base_frame`` is empty) and the scan's registered points in
    ``odom`` on ``/kentreg/cloud_registered`` (``--no-clouds``: without them), header stamps
    from the input scans; at the end one nav_msgs/Path on ``/kentreg/path`` and the map of the
    run (:class:`kentreg_ros.io.runmap.RunMap`, the node's map: the registered points of every
    accepted scan, one per ``--map-voxel`` voxel) as one sensor_msgs/PointCloud2 in ``odom``
    on ``/kentreg/map`` (:func:`kentreg_ros.io.bagwriter.write_odometry_mcap`).
``--map FILE``
    The same map as a PLY or PCD file (by suffix) for any point-cloud viewer.
``poses_tum.txt``, ``poses_kitti.txt``
    The trajectory ``T_odom_lidar`` (TUM with the scan stamps: ``evo_ape tum``).
``ground_truth_tum.txt``
    With ground truth: the reference poses associated with the scans (TUM), for evo.
``config.yaml``
    The effective configuration (loadable by ``--config`` and by the node).
``metrics.json``
    Health counts, the skipped scans, timings, per-scan steps and, with ground truth, the
    metrics below.
``trajectory.png``
    Top view of the estimate (aligned onto the ground truth when known) and per-pair errors.

Metrics (with ``--gt POSES`` or a ``/ground_truth`` topic in the bag)
----------------------------------------------------------------------
Per consecutive pair, the errors of Fahandezh-Saadi et al.: ``e_R = arccos((tr(R^T R_est) - 1)
/ 2)`` and ``e_t = ||t_est - t||`` (a pair *fails* when ``e_R > 2 deg`` or ``e_t > 0.2 m``);
RPE per frame and per metre travelled; ATE after SE(3) (Umeyama) alignment; and the KITTI
segment metric when the run is long enough to fill its 100 m segments. See
:mod:`kentreg_ros.eval`.

A scan that cannot be decoded (a malformed PointCloud2, an unreadable scan file) is skipped and
counted, as the ROS node does; the summary and ``metrics.json`` (``skipped``) name the first few
by input index, stamp and reason.

Exit status: 0 on success, 2 on bad input (one line on stderr; also when no scan could be
decoded), 130 when interrupted (the scans processed so far are still written out).
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from kentreg_ros import __version__
from kentreg_ros.cli import common
from kentreg_ros.core import Odometry
from kentreg_ros.eval.replay import (
    MAP_MAX_POINTS,
    MAP_VOXEL_SIZE,
    ReplayOptions,
    finish_replay,
    open_replay,
    run_replay,
)
from kentreg_ros.eval.report import format_summary
from kentreg_ros.io.recordings import GROUND_TRUTH_TOPIC

logger = logging.getLogger('kentreg_ros.cli.replay')  # also when run as __main__

PROG = 'kentreg_replay'


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_replay``."""
    parser = common.ArgumentParser(
        prog=PROG,
        description='Run kentreg odometry over a bag or a scan folder; write the trajectory '
        '(MCAP, TUM, KITTI), the metrics against ground truth and a plot.',
    )
    add = parser.add_argument
    add(
        'input',
        metavar='BAG_OR_FOLDER',
        help='rosbag2 folder or .mcap/.db3/.bag file with one PointCloud2 topic (or --topic), '
        'or a folder of scan files (.pcd, .ply, .bin, .csv) in natural order',
    )
    add('--topic', help='PointCloud2 topic, when the bag has several')
    common.add_config_options(parser)
    add(
        '--out',
        type=Path,
        help='output folder (default: results/<timestamp>/, and results/latest points to it)',
    )
    add(
        '--gt',
        type=Path,
        metavar='POSES',
        help='ground-truth poses (TUM, KITTI, BALM alidarPose.csv, ETH pose_scanner_leica.csv); '
        f"default: the bag's {GROUND_TRUTH_TOPIC} topic, or a pose file beside the scans",
    )
    add_replay_options(parser, map_file=True)
    add('--no-progress', action='store_true', help='no progress bar')
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument('-v', '--verbose', action='store_true', help='log every step')
    verbosity.add_argument('-q', '--quiet', action='store_true', help='log errors only')
    add('--version', action='version', version=f'%(prog)s {__version__}')
    return parser


def add_replay_options(parser: argparse.ArgumentParser, *, map_file: bool = False) -> None:
    """The replay's options that apply to any input (``--gt-topic`` to ``--no-plot``; with
    ``map_file`` also ``--map FILE``), shared by ``kentreg_replay`` and ``kentreg_batch``."""
    add = parser.add_argument
    add(
        '--gt-topic',
        default=GROUND_TRUTH_TOPIC,
        help=f'ground-truth topic of the bag (default {GROUND_TRUTH_TOPIC})',
    )
    add(
        '--max-scans',
        type=common.positive_int,
        metavar='N',
        help='process N scans (after --stride)',
    )
    add(
        '--start',
        type=common.non_negative_int,
        default=0,
        metavar='N',
        help='skip the first N scans',
    )
    add(
        '--stride',
        type=common.positive_int,
        default=1,
        metavar='N',
        help='process every N-th scan only (start, start+N, ...), stamps unchanged: a '
        'frame-skipping stress test; pairs and metrics join consecutive processed scans '
        '(default 1: every scan)',
    )
    add('--odom-frame', default='odom', help='frame of the output poses (default odom)')
    add(
        '--child-frame',
        help="child frame of the output poses (default: the scans' sensor frame; the lidar "
        'pose is written as is, so give base_link only if the two frames coincide)',
    )
    if map_file:
        add(
            '--map',
            type=Path,
            metavar='FILE',
            help='also write the map of the run (the registered points of every accepted scan at '
            'its pose, one point per --map-voxel voxel, odometry frame; what kentreg_node saves) '
            'to FILE (.ply or .pcd); the MCAP carries it anyway',
        )
    add(
        '--map-voxel',
        type=common.positive_float,
        default=MAP_VOXEL_SIZE,
        metavar='M',
        help=f"voxel edge of the map in metres (default {MAP_VOXEL_SIZE}, the node's "
        f'map_voxel_size; it doubles when the map passes {MAP_MAX_POINTS} points)',
    )
    add(
        '--no-clouds',
        action='store_true',
        help='leave the per-scan registered clouds out of odometry.mcap (a smaller file)',
    )
    add('--no-plot', action='store_true', help='do not write trajectory.png')


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_replay``; returns the exit status (see the module docstring)."""
    return common.run_main(PROG, lambda: _replay(argv))


def _replay(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.ERROR if args.quiet else logging.WARNING
    with common.logging_to_stderr(PROG, level):
        return _run(args, [PROG, *(sys.argv[1:] if argv is None else argv)])


def _run(args: argparse.Namespace, command: list[str]) -> int:
    cfg = common.config_from_args(args)
    recording = open_replay(args.input, replay_options(args))
    out = args.out if args.out is not None else default_out_dir()
    odometry = Odometry(cfg)
    with common.progress_bar(PROG, recording.n_selected, enabled=not args.no_progress) as bar:

        def advance(_: object) -> None:
            bar.update(1)
            if odometry.n_failed:
                bar.set_postfix(failed=odometry.n_failed, refresh=False)

        run = run_replay(recording, odometry, on_step=advance if bar is not None else None)
    summary = finish_replay(
        recording,
        run,
        cfg,
        out,
        config_label=str(args.config) if args.config else 'defaults',
        overrides=args.overrides,
        command=command,
    )
    if args.out is None:
        _link_latest(out)
    print(format_summary(summary.report, out, prog=PROG))
    if run.error is not None:
        print(
            f'{PROG}: error: {run.error} (results of the {len(run.steps)} scans read are in '
            f'{out}/)',
            file=sys.stderr,
        )
        return common.EXIT_BAD_INPUT
    if run.interrupted:
        print(f'{PROG}: interrupted after {len(run.steps)} scans', file=sys.stderr)
        return common.EXIT_INTERRUPTED
    return common.EXIT_OK


def replay_options(args: argparse.Namespace) -> ReplayOptions:
    """The :class:`~kentreg_ros.eval.replay.ReplayOptions` of parsed replay options (those of
    :func:`add_replay_options`; ``--gt`` and ``--map`` when the parser has them)."""
    return ReplayOptions(
        topic=args.topic,
        gt=getattr(args, 'gt', None),
        gt_topic=args.gt_topic,
        start=args.start,
        stride=args.stride,
        max_scans=args.max_scans,
        odom_frame=args.odom_frame,
        child_frame=args.child_frame,
        map_path=getattr(args, 'map', None),
        map_voxel=args.map_voxel,
        clouds=not args.no_clouds,
        plot=not args.no_plot,
    )


def default_out_dir(root: Path = Path('results')) -> Path:
    """``results/<YYYYmmdd-HHMMSS>`` (with ``-2``, ``-3``, ... if taken)."""
    stamp = datetime.datetime.now().strftime('%Y%m%d-%H%M%S')
    out = root / stamp
    n = 2
    while out.exists():
        out = root / f'{stamp}-{n}'
        n += 1
    return out


def _link_latest(out: Path) -> None:
    link = out.parent / 'latest'
    tmp = out.parent / f'.latest-{os.getpid()}'
    try:
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(out.name, target_is_directory=True)
        os.replace(tmp, link)
    except OSError as exc:
        logger.warning('Cannot point %s at %s: %s', link, out, exc)


if __name__ == '__main__':
    sys.exit(main())
