"""``kentreg_node`` whose worker waits while a hold file exists: a test double for a slow node.

``test_node.py`` overloads the node by holding its worker on one scan while the test publishes
more: how many scans the node drops then follows from the queue policy alone, not from how
fast the machine registers scans compared with the rate the test publishes at. Everything else
is the real node (``kentreg_ros.ros.node.main``); only its worker's ``ScanWorker.process``
first waits, before each scan, until the file named by ``KENTREG_TEST_HOLD_FILE`` is gone (the
executor thread, subscription, services and diagnostics keep running meanwhile).

Run as ``python test/gated_node.py --ros-args ...`` with ``KENTREG_TEST_HOLD_FILE`` set.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from kentreg_ros.ros import node, worker

#: How often the held worker looks at the hold file (s): the latency of releasing it.
POLL_S = 0.005

_process = worker.ScanWorker.process


def _held_process(self: worker.ScanWorker, scan: Any, settings: Any) -> None:
    hold = Path(os.environ['KENTREG_TEST_HOLD_FILE'])
    while hold.exists():
        time.sleep(POLL_S)
    _process(self, scan, settings)


worker.ScanWorker.process = _held_process  # type: ignore[method-assign]

if __name__ == '__main__':
    raise SystemExit(node.main())
