"""How the odometry runs in a process: its prepare stage here or in a worker process.

The core (:mod:`kentreg_ros.core`) is numpy/scipy registration and odometry; this package holds
what runs it on more than one core: the worker process, its messages and the hand-over of
scans through ``/dev/shm`` (:mod:`.preparer`, :mod:`.worker`, :mod:`.messages`), and what a
caller such as the node needs of a preparer that works ahead (:mod:`.pipeline`).
It imports the core, never the node.
"""

from kentreg_ros.runtime.pipeline import ScanPreparer, close_after
from kentreg_ros.runtime.preparer import (
    MAX_OPEN_JOBS,
    PipelineError,
    PipelineStats,
    ProcessPreparer,
)

__all__ = [
    'MAX_OPEN_JOBS',
    'PipelineError',
    'PipelineStats',
    'ProcessPreparer',
    'ScanPreparer',
    'close_after',
]
