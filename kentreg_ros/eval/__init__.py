"""What judges a run: pair errors, RPE/ATE/KITTI, ground-truth association, the report, plots.

Never imports rclpy; matplotlib only when a plot is drawn (:mod:`kentreg_ros.eval.plotting`).
The modules: :mod:`~kentreg_ros.eval.metrics` (pair errors and failures, RPE, ATE),
:mod:`~kentreg_ros.eval.kitti` (the KITTI segment metric), :mod:`~kentreg_ros.eval.groundtruth`
(reference poses projected onto SO(3) and associated with the scans), :mod:`~kentreg_ros.eval.run`
(a timed odometry run over recorded scans), :mod:`~kentreg_ros.eval.report` (the run's metrics,
``metrics.json`` and the printed summary) and :mod:`~kentreg_ros.eval.plotting`.
"""

from kentreg_ros.eval.groundtruth import GT_TOLERANCE_S, GroundTruth, associate, orthonormalize
from kentreg_ros.eval.metrics import FAIL_ROTATION_DEG, FAIL_TRANSLATION_M, failed_pairs
from kentreg_ros.eval.report import (
    Evaluation,
    evaluate,
    evaluate_run,
    format_summary,
    jsonable,
    run_report,
    speed_summary,
    step_record,
)
from kentreg_ros.eval.run import OdometryRun, run_odometry

__all__ = [
    'FAIL_ROTATION_DEG',
    'FAIL_TRANSLATION_M',
    'GT_TOLERANCE_S',
    'Evaluation',
    'GroundTruth',
    'OdometryRun',
    'associate',
    'evaluate',
    'evaluate_run',
    'failed_pairs',
    'format_summary',
    'jsonable',
    'orthonormalize',
    'run_odometry',
    'run_report',
    'speed_summary',
    'step_record',
]
