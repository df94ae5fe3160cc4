"""Many recordings at once: ``kentreg_batch`` replays each input on a worker of a cluster.

:mod:`~kentreg_ros.batch.inputs` finds the inputs and names their output folders,
:mod:`~kentreg_ros.batch.job` replays one input in a worker (the replay's own code,
:func:`kentreg_ros.eval.replay.replay`) and marks it finished,
:mod:`~kentreg_ros.batch.engine` runs the jobs on Dask's distributed scheduler (or in this
process), :mod:`~kentreg_ros.batch.summary` writes ``summary.json`` and ``summary.md``, and
:mod:`~kentreg_ros.batch.runner` ties them together. Never imports rclpy; Dask only when a
cluster is used.
"""

from kentreg_ros.batch.inputs import BatchInputError, discover_inputs, output_names
from kentreg_ros.batch.job import BatchJob, InputEntry, InputStatus, run_job
from kentreg_ros.batch.runner import BatchResult, plan_batch, run_batch

__all__ = [
    'BatchInputError',
    'BatchJob',
    'BatchResult',
    'InputEntry',
    'InputStatus',
    'discover_inputs',
    'output_names',
    'plan_batch',
    'run_batch',
    'run_job',
]
