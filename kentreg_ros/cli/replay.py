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
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from kentreg_ros import __version__
from kentreg_ros.cli import common
from kentreg_ros.core import KentRegConfig, Odometry
from kentreg_ros.eval import GroundTruth, OdometryRun, evaluate_run, run_odometry, run_report
from kentreg_ros.eval.report import (
    Evaluation,
    format_summary,
    jsonable,
    skipped_record,
    skipped_text,
    stride_text,
)
from kentreg_ros.io.mapfile import MAP_SUFFIXES
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.recordings import GROUND_TRUTH_TOPIC
from kentreg_ros.io.sources import ScanSource

logger = logging.getLogger('kentreg_ros.cli.replay')  # also when run as __main__

PROG = 'kentreg_replay'
#: Default voxel edge and size bound of the run's map: the node's (``map_voxel_size``,
#: ``map_max_points``), so the replay's map and the node's ~/save_map are the same map.
MAP_VOXEL_SIZE = NodeSettings().map_voxel_size
MAP_MAX_POINTS = NodeSettings().map_max_points


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
    add('--no-progress', action='store_true', help='no progress bar')
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument('-v', '--verbose', action='store_true', help='log every step')
    verbosity.add_argument('-q', '--quiet', action='store_true', help='log errors only')
    add('--version', action='version', version=f'%(prog)s {__version__}')
    return parser


def open_input(args: argparse.Namespace) -> tuple[ScanSource, GroundTruth | None]:
    """The scan source and its ground truth (``--gt``, the bag's topic, a file beside scans)."""
    from kentreg_ros.io.bags import is_bag
    from kentreg_ros.io.recordings import open_recording

    path = Path(args.input)
    if not path.exists():
        raise common.CliError(f'{path}: no such file or folder')
    if args.gt is not None and not args.gt.is_file():
        raise common.CliError(f'--gt {args.gt}: no such file')
    if args.topic is not None and not is_bag(path):
        raise common.CliError(f'--topic applies to bags; {path} is not a bag')
    # Every per-point field is decoded: a per-point time field feeds the deskewing.
    recording = open_recording(
        path, topic=args.topic, poses=args.gt, poses_topic=args.gt_topic, fields=None
    )
    if recording.reference is None:
        return recording.source, None
    return recording.source, GroundTruth(recording.reference, recording.reference_origin)


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
    source, gt = open_input(args)
    if args.map is not None and args.map.suffix.lower() not in MAP_SUFFIXES:
        raise common.CliError(
            f'--map {args.map}: expected a file ending in {" or ".join(MAP_SUFFIXES)}'
        )
    if args.start >= len(source):
        raise common.CliError(f'--start {args.start}: the input has only {len(source)} scans')
    out = args.out if args.out is not None else default_out_dir()
    logger.info('Reading %s', source.description)
    odometry = Odometry(cfg)
    total = len(range(args.start, len(source), args.stride)[: args.max_scans])
    with common.progress_bar(PROG, total, enabled=not args.no_progress) as bar:

        def advance(_: object) -> None:
            bar.update(1)
            if odometry.n_failed:
                bar.set_postfix(failed=odometry.n_failed, refresh=False)

        run = run_odometry(
            source,
            odometry,
            start=args.start,
            max_scans=args.max_scans,
            stride=args.stride,
            on_step=advance if bar is not None else None,
            map_voxel_size=args.map_voxel,
            map_max_points=MAP_MAX_POINTS,
        )
    if not run.steps:
        if run.error is None and run.skipped:
            first = run.skipped[0]
            raise common.CliError(
                f'{args.input}: none of the {run.n_skipped} scans read could be decoded; the '
                f'first: {skipped_text(skipped_record(first))}'
            )
        raise common.CliError(run.error or f'{args.input}: no scan was read')
    evaluation, note = evaluate_run(run, gt)
    report: dict[str, Any] = {
        'kentreg_version': __version__,
        'command': command,
        'input': {
            'path': str(args.input),
            'description': source.description,
            'start': args.start,
            'stride': args.stride,
            'n_scans': len(run.steps),
            'n_nonfinite_dropped': int(getattr(source, 'n_dropped', 0)),
            'frame_id': run.steps[0].frame_id,
        },
        'mode': cfg.mode,
        'config': str(args.config) if args.config else 'defaults',
        'overrides': list(args.overrides),
        **run_report(run, evaluation, note),
    }
    title = f'kentreg ({cfg.mode}): {Path(args.input).name}'
    if args.stride > 1:
        title += f', {stride_text(args.stride)}'
    write_outputs(
        out,
        run,
        cfg,
        evaluation,
        report,
        odom_frame=args.odom_frame,
        child_frame=args.child_frame or run.steps[0].frame_id or 'base_link',
        plot=not args.no_plot,
        title=title,
        map_path=args.map,
        clouds=not args.no_clouds,
    )
    if args.out is None:
        _link_latest(out)
    print(format_summary(report, out, prog=PROG))
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


def write_outputs(
    out: Path,
    run: OdometryRun,
    cfg: KentRegConfig,
    evaluation: Evaluation | None,
    report: dict[str, Any],
    *,
    odom_frame: str,
    child_frame: str,
    plot: bool,
    title: str,
    map_path: Path | None = None,
    clouds: bool = True,
) -> list[str]:
    """Write every output file into ``out`` (and the map to ``map_path``); return the names
    written into ``out``."""
    from kentreg_ros.io.bagwriter import write_odometry_mcap
    from kentreg_ros.io.params import dump_config
    from kentreg_ros.io.poses import write_kitti, write_tum

    out.mkdir(parents=True, exist_ok=True)
    map_points = run.map.points if run.map is not None and len(run.map) else None
    counts = write_odometry_mcap(
        out / 'odometry.mcap',
        run.steps,
        odom_frame=odom_frame,
        child_frame=child_frame,
        map_points=map_points,
        clouds=clouds,
    )
    report['odometry_mcap'] = {
        'topics': counts,
        'odom_frame': odom_frame,
        'child_frame': child_frame,
    }
    write_tum(out / 'poses_tum.txt', run.stamps_ns, run.poses)
    write_kitti(out / 'poses_kitti.txt', run.poses)
    written = ['odometry.mcap', 'poses_tum.txt', 'poses_kitti.txt']
    if evaluation is not None:
        write_tum(out / 'ground_truth_tum.txt', evaluation.stamps_ns, evaluation.T_gt)
        written.append('ground_truth_tum.txt')
    if map_path is not None and map_points is not None:
        from kentreg_ros.io.mapfile import write_map

        map_path.parent.mkdir(parents=True, exist_ok=True)
        write_map(map_path, map_points)
        report['map'] = {
            'path': str(map_path),
            'points': len(map_points),
            'voxel_size': run.map.voxel_size if run.map is not None else 0.0,
        }
    (out / 'config.yaml').write_text(dump_config(cfg))
    written.append('config.yaml')
    if plot and _plot(out / 'trajectory.png', run, evaluation, title):
        written.append('trajectory.png')
    report['files'] = written + ['metrics.json']
    (out / 'metrics.json').write_text(json.dumps(jsonable(report), indent=2) + '\n')
    written.append('metrics.json')
    return written


def _plot(path: Path, run: OdometryRun, evaluation: Evaluation | None, title: str) -> bool:
    try:
        from kentreg_ros.eval.plotting import plot_run

        plot_run(path, run, evaluation, title=title)
    except ImportError as exc:
        logger.warning('No trajectory.png: %s (pip install matplotlib).', exc)
        return False
    return True


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
