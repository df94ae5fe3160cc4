"""One replay of a recording: open it, run the odometry over it, evaluate it, write its outputs.

What ``kentreg_replay`` does with its input and ``kentreg_batch`` with each of its inputs (the
same code, so the same files and poses): :func:`open_replay` opens the input and checks the
options against it, :func:`run_replay` feeds its scans to the odometry
(:func:`~kentreg_ros.eval.run.run_odometry`), :func:`finish_replay` evaluates the run against the
ground truth and writes every output file (:func:`write_outputs`), and :func:`replay` does all
three. The result is a :class:`ReplaySummary`: the run, what ``metrics.json`` holds, the files.

The messages of :class:`ReplayError` name the options as the command lines spell them
(``--gt``, ``--start``), since they are what a user reads.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from kentreg_ros import __version__
from kentreg_ros.core import KentRegConfig, KentRegError, Odometry, OdometryStep
from kentreg_ros.eval.groundtruth import GroundTruth
from kentreg_ros.eval.report import (
    Evaluation,
    evaluate_run,
    jsonable,
    run_report,
    skipped_record,
    skipped_text,
    stride_text,
)
from kentreg_ros.eval.run import OdometryRun, run_odometry
from kentreg_ros.io.mapfile import MAP_SUFFIXES
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.recordings import GROUND_TRUTH_TOPIC
from kentreg_ros.io.sources import ScanSource

logger = logging.getLogger(__name__)

#: Default voxel edge and size bound of the run's map: the node's (``map_voxel_size``,
#: ``map_max_points``), so the replay's map and the node's ~/save_map are the same map.
MAP_VOXEL_SIZE = NodeSettings().map_voxel_size
MAP_MAX_POINTS = NodeSettings().map_max_points


class ReplayError(KentRegError, ValueError):
    """An input or an option the replay cannot take; the message names it."""


@dataclass(frozen=True)
class ReplayOptions:
    """How to read an input and what to write of its run (``kentreg_replay``'s options).

    Attributes
    ----------
    topic : str or None
        The bag's PointCloud2 topic (bags only; None: its one PointCloud2 topic).
    gt : Path or None
        A ground-truth pose file; None: the bag's ``gt_topic`` or a pose file beside the scans.
    gt_topic : str
        The bag's ground-truth topic.
    start, stride, max_scans : int, int, int or None
        The scans processed: ``start, start + stride, ...``, at most ``max_scans``.
    odom_frame : str
        Frame of the output poses.
    child_frame : str or None
        Child frame of the output poses; None: the scans' frame (``base_link`` without one).
    map_path : Path or None
        Also write the run's map there (``.ply`` or ``.pcd``).
    map_voxel : float
        Voxel edge of the run's map (m).
    clouds : bool
        Write the registered clouds into ``odometry.mcap``.
    plot : bool
        Write ``trajectory.png``.
    """

    topic: str | None = None
    gt: Path | None = None
    gt_topic: str = GROUND_TRUTH_TOPIC
    start: int = 0
    stride: int = 1
    max_scans: int | None = None
    odom_frame: str = 'odom'
    child_frame: str | None = None
    map_path: Path | None = None
    map_voxel: float = MAP_VOXEL_SIZE
    clouds: bool = True
    plot: bool = True


@dataclass
class ReplayInput:
    """An opened input (:func:`open_replay`): its scans, ground truth and the options taken."""

    #: The input as the user gave it (it names the input in the report and in messages).
    name: str
    source: ScanSource
    gt: GroundTruth | None
    options: ReplayOptions

    @property
    def n_selected(self) -> int:
        """Scans the run will take (after ``start``, ``stride`` and ``max_scans``)."""
        opts = self.options
        return len(range(opts.start, len(self.source), opts.stride)[: opts.max_scans])


@dataclass
class ReplaySummary:
    """What a replay did (:func:`finish_replay`).

    Attributes
    ----------
    out : Path
        The output folder.
    run : OdometryRun
        The odometry's run.
    report : dict
        What ``metrics.json`` holds (JSON-ready after :func:`~kentreg_ros.eval.report.jsonable`).
    files : list of str
        The files written into ``out``.
    """

    out: Path
    run: OdometryRun
    report: dict[str, Any]
    files: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        """Every selected scan was read: not interrupted, no read error."""
        return not self.run.interrupted and self.run.error is None

    @property
    def n_scans(self) -> int:
        """Scans processed."""
        return len(self.run.steps)

    @property
    def health(self) -> dict[str, int]:
        """Steps per health (``first``, ``ok``, ... ``rejected``)."""
        return dict(self.report['health'])

    @property
    def ms_per_scan(self) -> float:
        """Mean milliseconds per scan."""
        return float(self.report['speed']['ms_per_scan']['mean'])

    @property
    def failed_pairs(self) -> tuple[int, int] | None:
        """Failed pairs and pairs against the ground truth; None without one."""
        gt = self.report.get('ground_truth')
        if gt is None:
            return None
        return int(gt['pairs']['n_failed']), int(gt['pairs']['count'])

    @property
    def ate_m(self) -> float | None:
        """ATE RMSE after SE(3) alignment (m); None without ground truth or below 3 poses."""
        gt = self.report.get('ground_truth')
        if gt is None or gt['ate'] is None:
            return None
        return float(gt['ate']['rmse'])


def open_replay(name: str, options: ReplayOptions) -> ReplayInput:
    """Open the bag or scan folder ``name`` with its ground truth and check ``options`` on it.

    The ground truth is ``options.gt``, else the bag's ``options.gt_topic``, else a pose file
    beside the scans. Every per-point field is decoded (a per-point time feeds the deskewing).

    Raises
    ------
    ReplayError
        No such input or ``--gt`` file, ``--topic`` on a folder, a map file of an unknown kind,
        ``--start`` beyond the input.
    KentRegError, ValueError, OSError
        The input cannot be read (see :func:`~kentreg_ros.io.recordings.open_recording`).
    """
    from kentreg_ros.io.bags import is_bag
    from kentreg_ros.io.recordings import open_recording

    path = Path(name)
    if not path.exists():
        raise ReplayError(f'{path}: no such file or folder')
    if options.gt is not None and not options.gt.is_file():
        raise ReplayError(f'--gt {options.gt}: no such file')
    if options.topic is not None and not is_bag(path):
        raise ReplayError(f'--topic applies to bags; {path} is not a bag')
    recording = open_recording(
        path,
        topic=options.topic,
        poses=options.gt,
        poses_topic=options.gt_topic,
        fields=None,
    )
    gt = None
    if recording.reference is not None:
        gt = GroundTruth(recording.reference, recording.reference_origin)
    source = recording.source
    if options.map_path is not None and options.map_path.suffix.lower() not in MAP_SUFFIXES:
        raise ReplayError(
            f'--map {options.map_path}: expected a file ending in {" or ".join(MAP_SUFFIXES)}'
        )
    if options.start >= len(source):
        raise ReplayError(f'--start {options.start}: the input has only {len(source)} scans')
    return ReplayInput(name, source, gt, options)


def run_replay(
    recording: ReplayInput,
    odometry: Odometry,
    *,
    on_step: Callable[[OdometryStep], object] | None = None,
) -> OdometryRun:
    """Feed the selected scans of ``recording`` to ``odometry`` (a fresh one), building the
    run's map (:func:`~kentreg_ros.eval.run.run_odometry`); Ctrl-C ends it early."""
    logger.info('Reading %s', recording.source.description)
    opts = recording.options
    return run_odometry(
        recording.source,
        odometry,
        start=opts.start,
        max_scans=opts.max_scans,
        stride=opts.stride,
        on_step=on_step,
        map_voxel_size=opts.map_voxel,
        map_max_points=MAP_MAX_POINTS,
    )


def finish_replay(
    recording: ReplayInput,
    run: OdometryRun,
    config: KentRegConfig,
    out: Path,
    *,
    config_label: str = 'defaults',
    overrides: Sequence[str] = (),
    command: Sequence[str] = (),
) -> ReplaySummary:
    """Evaluate ``run`` against the input's ground truth and write every output into ``out``.

    A run cut short (a read error, Ctrl-C) is written as far as it went; its summary says so
    (:attr:`ReplaySummary.complete`).

    Parameters
    ----------
    recording : ReplayInput
    run : OdometryRun
        :func:`run_replay` of ``recording``.
    config : KentRegConfig
        The configuration the odometry ran with (written as ``config.yaml``).
    out : Path
        The output folder (created).
    config_label, overrides, command : str, sequence of str, sequence of str
        Recorded in ``metrics.json``: the parameter file (or 'defaults'), the ``--set``
        items and the command line.

    Raises
    ------
    ReplayError
        No scan was processed (nothing is written then).
    """
    opts = recording.options
    if not run.steps:
        if run.error is None and run.skipped:
            first = run.skipped[0]
            raise ReplayError(
                f'{recording.name}: none of the {run.n_skipped} scans read could be decoded; '
                f'the first: {skipped_text(skipped_record(first))}'
            )
        raise ReplayError(run.error or f'{recording.name}: no scan was read')
    evaluation, note = evaluate_run(run, recording.gt)
    report: dict[str, Any] = {
        'kentreg_version': __version__,
        'command': list(command),
        'input': {
            'path': recording.name,
            'description': recording.source.description,
            'start': opts.start,
            'stride': opts.stride,
            'n_scans': len(run.steps),
            'n_nonfinite_dropped': int(getattr(recording.source, 'n_dropped', 0)),
            'frame_id': run.steps[0].frame_id,
        },
        'mode': config.mode,
        'config': config_label,
        'overrides': list(overrides),
        **run_report(run, evaluation, note),
    }
    title = f'kentreg ({config.mode}): {Path(recording.name).name}'
    if opts.stride > 1:
        title += f', {stride_text(opts.stride)}'
    files = write_outputs(
        out,
        run,
        config,
        evaluation,
        report,
        odom_frame=opts.odom_frame,
        child_frame=opts.child_frame or run.steps[0].frame_id or 'base_link',
        plot=opts.plot,
        title=title,
        map_path=opts.map_path,
        clouds=opts.clouds,
    )
    return ReplaySummary(out, run, report, files)


def replay(
    name: str,
    config: KentRegConfig,
    out: Path,
    options: ReplayOptions,
    *,
    config_label: str = 'defaults',
    overrides: Sequence[str] = (),
    command: Sequence[str] = (),
) -> ReplaySummary:
    """:func:`open_replay`, :func:`run_replay` with a fresh odometry, :func:`finish_replay`.

    Raises
    ------
    ReplayError, KentRegError, ValueError, OSError
        As those three.
    """
    recording = open_replay(name, options)
    run = run_replay(recording, Odometry(config))
    return finish_replay(
        recording,
        run,
        config,
        out,
        config_label=config_label,
        overrides=overrides,
        command=command,
    )


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
    from kentreg_ros.io.paramfile import dump_config
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
