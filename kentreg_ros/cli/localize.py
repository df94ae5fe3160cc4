"""``kentreg_localize``: where the scans of a recording are in a saved map.

By default the recording is tracked: the odometry runs over the scans as in ``kentreg_replay``
and each prepared scan, with its odometry pose, goes to the localizer, which searches the map
from no start until ``localization.agreement`` consecutive scans agree, then tracks
(:mod:`kentreg_ros.eval.localization`). ``--global-each`` localizes every scan on its own from no
start instead (what the localization benchmark measures).

Examples
--------
The sample's scans in a map written by the replay (the map's trajectory, ``poses_tum.txt``,
lies beside it)::

    kentreg_replay bags/balm_50 --map run/map.ply --out run
    kentreg_localize run/map.ply bags/balm_50

Every scan on its own, a map from another SLAM system with its trajectory::

    kentreg_localize site.pcd scans/ --map-trajectory site_poses.txt --global-each

Inputs
------
MAP
    A PLY or PCD point cloud (:func:`kentreg_ros.io.mapload.load_point_map`). The trajectory it
    was recorded from (``trajectory_tum.txt`` or ``poses_tum.txt`` beside it, or
    ``--map-trajectory``) orients its normals; it is prepared once and cached beside it
    (``--no-cache``: neither read nor written).
SCANS
    Anything ``kentreg_replay`` reads: a rosbag2 folder or file, a ROS 1 bag, a scan folder.

Outputs in ``--out`` (default ``results/<timestamp>/``)
-------------------------------------------------------
``localization.json``
    One entry per scan read: ``index`` (in the input), ``stamp_ns``, ``status`` (tracking: the
    localizer's state after the scan, ``searching``, ``localized``, ``lost`` or ``ambiguous``;
    ``--global-each``: ``localized``, ``ambiguous`` or ``not_found``), ``T_map_scan`` (4x4
    nested lists, null unless this scan was placed), ``fit``, ``message``, ``ms`` (the
    localization's time) and ``searched``.
``poses_tum.txt``
    The placed scans' poses in the map (TUM).
``config.yaml``
    The effective configuration.
``summary.json``
    Counts per status, times and, with a reference (``--gt``, the bag's topic or a pose file
    beside the scans) in the map's frame, the share localized, those within 0.5 m and 2 deg of
    the reference and the false accepts (placed but farther off). The reference is in the
    map's frame when the map was built at the reference poses (its trajectory is at them at
    the same stamps, or ``--reference-in-map-frame`` says so); otherwise the comparison is not
    possible, and the summary says why.

Exit status: 0 on success, 2 on bad input (one line on stderr), 130 when interrupted (the scans
placed so far are written out).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kentreg_ros import __version__
from kentreg_ros.cli import common
from kentreg_ros.cli.replay import default_out_dir
from kentreg_ros.core import KentRegConfig, PointMap
from kentreg_ros.eval import GroundTruth
from kentreg_ros.eval.localization import (
    LocalizationRun,
    LocalizedScan,
    localize_each,
    reference_frame_note,
    score_localization,
    track_recording,
)
from kentreg_ros.eval.report import jsonable
from kentreg_ros.io.poses import Trajectory
from kentreg_ros.io.recordings import GROUND_TRUTH_TOPIC, Recording

logger = logging.getLogger('kentreg_ros.cli.localize')  # also when run as __main__

PROG = 'kentreg_localize'


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``kentreg_localize``."""
    parser = common.ArgumentParser(
        prog=PROG,
        description='Localize the scans of a bag or a scan folder in a saved point-cloud map: '
        'track them with the odometry, or (--global-each) each on its own from no start.',
    )
    add = parser.add_argument
    add('map', metavar='MAP', type=Path, help='the map: a PLY or PCD point cloud')
    add('scans', metavar='SCANS', help='rosbag2 folder or .mcap/.db3/.bag file, or a scan folder')
    add('--topic', help='PointCloud2 topic, when the bag has several')
    add(
        '--map-trajectory',
        type=Path,
        metavar='POSES',
        help='the poses the map was recorded from (any pose file); default: '
        'trajectory_tum.txt or poses_tum.txt beside the map',
    )
    add('--no-cache', action='store_true', help='neither read nor write the prepared map cache')
    add(
        '--global-each',
        action='store_true',
        help='localize every scan on its own from no start (no odometry, no tracking)',
    )
    common.add_config_options(parser)
    add('--out', type=Path, help='output folder (default: results/<timestamp>/)')
    add(
        '--gt',
        type=Path,
        metavar='POSES',
        help=f"reference poses; default: the bag's {GROUND_TRUTH_TOPIC} topic, or a pose file "
        'beside the scans',
    )
    add('--gt-topic', default=GROUND_TRUTH_TOPIC, help='reference topic of the bag')
    add(
        '--reference-in-map-frame',
        action='store_true',
        help="compare with the reference without checking that the map's trajectory is at "
        'its poses (a reference known to be in the frame the map was built in)',
    )
    add('--start', type=common.non_negative_int, default=0, metavar='N', help='skip N scans')
    add(
        '--stride',
        type=common.positive_int,
        default=1,
        metavar='N',
        help='every N-th scan only (default 1)',
    )
    add('--max-scans', type=common.positive_int, metavar='N', help='N scans at most')
    add('--no-progress', action='store_true', help='no progress bar')
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument('-v', '--verbose', action='store_true', help='log every step')
    verbosity.add_argument('-q', '--quiet', action='store_true', help='log errors only')
    add('--version', action='version', version=f'%(prog)s {__version__}')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``kentreg_localize``; returns the exit status (module docstring)."""
    return common.run_main(PROG, lambda: _localize(argv))


def _localize(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.ERROR if args.quiet else logging.WARNING
    with common.logging_to_stderr(PROG, level):
        return _run(args)


def _open(args: argparse.Namespace) -> tuple[Recording, Path | None]:
    """The recording, and the map's trajectory file (given, or found beside the map)."""
    from kentreg_ros.io.bags import is_bag
    from kentreg_ros.io.mapload import trajectory_beside
    from kentreg_ros.io.recordings import open_recording

    for option, path in (('', args.map), ('', Path(args.scans)), ('--gt ', args.gt),
                         ('--map-trajectory ', args.map_trajectory)):  # fmt: skip
        if path is not None and not path.exists():
            raise common.CliError(f'{option}{path}: no such file or folder')
    if args.topic is not None and not is_bag(Path(args.scans)):
        raise common.CliError(f'--topic applies to bags; {args.scans} is not a bag')
    recording = open_recording(
        args.scans, topic=args.topic, poses=args.gt, poses_topic=args.gt_topic,
        fields=() if args.global_each else None,  # per-point times deskew the tracked scans
    )  # fmt: skip
    return recording, args.map_trajectory or trajectory_beside(args.map)


def _run(args: argparse.Namespace) -> int:
    from kentreg_ros.io.mapload import load_point_map

    cfg = common.config_from_args(args)
    recording, trajectory = _open(args)
    source = recording.source
    if args.start >= len(source):
        raise common.CliError(f'--start {args.start}: the input has only {len(source)} scans')
    logger.info('Preparing the map %s', args.map)
    pmap = load_point_map(
        args.map, config=cfg, trajectory=args.map_trajectory, use_cache=not args.no_cache
    )
    total = len(range(args.start, len(source), args.stride)[: args.max_scans])
    select = {'start': args.start, 'max_scans': args.max_scans, 'stride': args.stride}
    with common.progress_bar(PROG, total, enabled=not args.no_progress) as bar:
        placed = 0

        def advance(status: object) -> None:
            nonlocal placed
            placed += str(status) == 'localized'
            if bar is not None:
                bar.set_postfix(localized=placed, refresh=False)
                bar.update(1)

        if args.global_each:
            run = localize_each(
                source, pmap, config=cfg, on_scan=lambda s: advance(s.status), **select
            )
        else:
            run = track_recording(source, pmap, config=cfg, on_scan=advance, **select)
    if not run.scans:
        raise common.CliError(run.error or f'{args.scans}: no scan could be read')
    out = args.out if args.out is not None else default_out_dir()
    summary = _summary(args, run, pmap, recording, trajectory)
    write_outputs(out, run, cfg, summary)
    print(format_summary(summary, out))
    if run.error is not None:
        print(f'{PROG}: error: {run.error} (the {len(run.scans)} scans read are in {out}/)',
              file=sys.stderr)  # fmt: skip
        return common.EXIT_BAD_INPUT
    if run.interrupted:
        print(f'{PROG}: interrupted after {len(run.scans)} scans', file=sys.stderr)
        return common.EXIT_INTERRUPTED
    return common.EXIT_OK


def _summary(
    args: argparse.Namespace,
    run: LocalizationRun,
    pmap: PointMap,
    recording: Recording,
    trajectory: Path | None,
) -> dict[str, Any]:
    """What ``summary.json`` holds (module docstring)."""
    ms = np.array([s.ms for s in run.scans])
    summary: dict[str, Any] = {
        'kentreg_version': __version__,
        'mode': run.mode,
        'map': {'path': str(args.map), 'points': len(pmap), 'oriented': pmap.oriented,
                'trajectory': None if trajectory is None else str(trajectory)},
        'input': {'path': str(args.scans), 'description': recording.source.description},
        'n_scans': len(run.scans),
        'counts': run.counts(),
        'ms': {'p50': float(np.percentile(ms, 50)), 'p95': float(np.percentile(ms, 95)),
               'max': float(ms.max())},
        'n_skipped': run.n_skipped,
    }  # fmt: skip
    if recording.reference is None:
        return summary
    gt = GroundTruth(recording.reference, recording.reference_origin)
    summary['reference'] = {'origin': gt.origin}
    note = '' if args.reference_in_map_frame else _frame_note(trajectory, gt)
    if note:
        summary['reference']['not_compared'] = note
    else:
        summary['reference'] |= score_localization(run.scans, gt).record()
    return summary


def _frame_note(trajectory: Path | None, gt: GroundTruth) -> str:
    """Why the reference cannot be compared with the map's poses ('' when it can)."""
    from kentreg_ros.core import KentRegError
    from kentreg_ros.io.poses import read_poses

    map_trajectory: Trajectory | None = None
    if trajectory is not None:
        try:
            map_trajectory = read_poses(trajectory)
        except (KentRegError, ValueError) as exc:
            return f"the map's trajectory {trajectory} cannot be read ({common.one_line(exc)})"
    return reference_frame_note(map_trajectory, gt)


def write_outputs(
    out: Path, run: LocalizationRun, cfg: KentRegConfig, summary: dict[str, Any]
) -> list[str]:
    """Write ``localization.json``, ``poses_tum.txt``, ``config.yaml`` and ``summary.json``
    into ``out``; return their names."""
    from kentreg_ros.io.paramfile import dump_config
    from kentreg_ros.io.poses import write_tum

    out.mkdir(parents=True, exist_ok=True)
    lines = [json.dumps(jsonable(s.record())) for s in run.scans]  # one line per scan
    (out / 'localization.json').write_text('[\n' + ',\n'.join(lines) + '\n]\n')
    placed: list[LocalizedScan] = run.localized
    stamps = np.array([s.stamp_ns for s in placed], dtype=np.int64)
    poses = np.array([s.T_map_scan for s in placed]).reshape(-1, 4, 4)
    write_tum(out / 'poses_tum.txt', stamps, poses)
    (out / 'config.yaml').write_text(dump_config(cfg))
    (out / 'summary.json').write_text(json.dumps(jsonable(summary), indent=2) + '\n')
    return ['localization.json', 'poses_tum.txt', 'config.yaml', 'summary.json']


def format_summary(summary: dict[str, Any], out: Path) -> str:
    """The printed summary: counts, times, the comparison with the reference."""
    counts = dict(summary['counts'])
    n, placed = summary['n_scans'], counts.pop('with_pose')
    statuses = ', '.join(f'{k} {v}' for k, v in counts.items())
    mode = 'each scan from no start' if summary['mode'] == 'global_each' else 'tracked'
    lines = [
        f'{PROG}: {n} scans of {summary["input"]["path"]} in {summary["map"]["path"]} '
        f'({summary["map"]["points"]} points), {mode}',
        f'  placed {placed} ({100 * placed / n:.0f} %); statuses: {statuses}',
        f'  ms per scan: p50 {summary["ms"]["p50"]:.0f}, p95 {summary["ms"]["p95"]:.0f}, '
        f'max {summary["ms"]["max"]:.0f}',
    ]
    ref = summary.get('reference')
    if ref is not None and 'not_compared' in ref:
        lines.append(f'  reference ({ref["origin"]}): not compared, {ref["not_compared"]}')
    elif ref is not None:
        bars = ref['bars']
        lines.append(
            f'  reference ({ref["origin"]}): {ref["n_localized"]} of {ref["n_referenced"]} '
            f'placed ({100 * ref["localized_share"]:.0f} %), {ref["n_correct"]} within '
            f'{bars["translation_m"]:g} m and {bars["rotation_deg"]:g} deg, false accepts '
            f'{ref["n_false_accepts"]}'
            + (f' (scans {ref["false_accepts"][:10]})' if ref['false_accepts'] else '')
        )
    lines.append(f'  written to {out}/')
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
