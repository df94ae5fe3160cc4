"""Scan path: which kentreg_ros functions one scan goes through, callback to published Odometry.

Feeds the first scans of a bag (``bags/balm_50`` by default) to a :class:`KentRegNode` built in
this process (a private rclpy context, its timers cancelled, nothing spinning it) exactly as its
subscription would (the bag's own CDR bytes, deserialized into an rclpy ``PointCloud2``), and
traces the ``--scan``-th one (1-based; the fourth by default, a scan past the first steps'
special cases) from ``KentRegNode._on_points`` to the odometry publisher's ``publish()``.

What is counted (the rules of docs/layout.md, "One scan's path"): every distinct kentreg_ros
function or method entered on the callback's thread (this one, during ``_on_points``) and on the
node's worker thread (until it calls the odometry publisher's ``publish()``); no dunders,
lambdas, comprehensions or generator expressions (the functions they call do count); properties
count. The scan-preparation and registration rooms and the kernels (``core/scan``,
``core/registration``, ``core/kernels``) count their entry point only (``prepare_scan``,
``register``, ``NeighborIndex.build``: nothing they call), the floor's helpers (the other
modules directly in ``core/``: ``geometry``, ``stopwatch``, ``config``, ...) not at all. With
``--pipeline process`` the worker process's side is not in the count (another process).

Prints the functions per module and the total, and writes them as JSON (``--json``)::

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST \\
    FASTRTPS_DEFAULT_PROFILES_FILE=$PWD/test/fastdds_localhost.xml \\
        python3 benchmarks/scan_path.py --pipeline sequential --json /tmp/path_seq.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: kentreg_ros rooms whose entry point alone counts (nothing they call).
ENTRY_ONLY = ('kentreg_ros.core.scan', 'kentreg_ros.core.registration', 'kentreg_ros.core.kernels')
#: The floor: modules directly in core/ (besides the facade and the rooms), never counted.
FLOOR_PREFIX = 'kentreg_ros.core.'
CORE_ROOMS = ('scan', 'registration', 'kernels', 'odometry', 'localization')
#: How long the script waits for the worker to be done with the scans (s).
TIMEOUT_S = 120.0


def module_of(frame: FrameType) -> str | None:
    """The kentreg_ros module a frame runs in (None outside the package)."""
    name = frame.f_globals.get('__name__', '')
    return name if isinstance(name, str) and name.startswith('kentreg_ros') else None


def is_floor(module: str) -> bool:
    """Whether ``module`` is one of the core's floor modules (``core.geometry``, ...)."""
    if not module.startswith(FLOOR_PREFIX):
        return False
    room = module[len(FLOOR_PREFIX) :].split('.')[0]
    return room not in CORE_ROOMS


def is_counted_name(name: str) -> bool:
    """Not a dunder, lambda, comprehension or generator expression."""
    return not (name.startswith('<') or (name.startswith('__') and name.endswith('__')))


def inside_entry_only_room(frame: FrameType) -> bool:
    """Whether a caller of ``frame`` runs in a room whose entry point alone counts."""
    caller = frame.f_back
    while caller is not None:
        module = module_of(caller)
        if module is not None and module.startswith(ENTRY_ONLY):
            return True
        caller = caller.f_back
    return False


@dataclass
class PathTrace:
    """The functions one scan enters, per thread; a profile function for every thread.

    Recording is armed for the callback's thread by :meth:`arm` and for the worker's thread by
    the same call; the worker's stops at the first call of ``stop_at`` (the odometry
    publisher's ``publish``) and the callback's when :meth:`disarm_callback` is called.
    """

    stop_at: Callable[[FrameType], bool]
    functions: dict[str, set[str]] = field(default_factory=dict)
    armed: set[int] = field(default_factory=set)
    worker_ident: int | None = None
    reached_publish: threading.Event = field(default_factory=threading.Event)

    def arm(self, callback_ident: int, worker_ident: int) -> None:
        """Record on these two threads from now on."""
        self.worker_ident = worker_ident
        self.armed = {callback_ident, worker_ident}

    def disarm_callback(self, callback_ident: int) -> None:
        """Stop recording on the callback's thread (its callback returned)."""
        self.armed.discard(callback_ident)

    def profile(self, frame: FrameType, event: str, arg: Any) -> None:
        """``sys.setprofile`` function: record a counted function on an armed thread."""
        if event != 'call':
            return
        ident = threading.get_ident()
        if ident not in self.armed:
            return
        if ident == self.worker_ident and self.stop_at(frame):
            self.armed.discard(ident)
            self.reached_publish.set()
            return
        module = module_of(frame)
        name = frame.f_code.co_qualname
        if module is None or is_floor(module) or not is_counted_name(frame.f_code.co_name):
            return
        if inside_entry_only_room(frame):
            return
        self.functions.setdefault(module, set()).add(name)


def bag_messages(bag: Path, topic: str, count: int) -> list[Any]:
    """The first ``count`` messages on ``topic`` as rclpy ``PointCloud2`` (from their CDR)."""
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import PointCloud2

    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        if not connections:
            raise SystemExit(f'{bag}: no topic {topic}')
        messages = []
        for _, _, raw in reader.messages(connections=connections):
            messages.append(deserialize_message(raw, PointCloud2))
            if len(messages) == count:
                return messages
    raise SystemExit(f'{bag}: {topic} has fewer than {count} messages')


def wait_for(done: Callable[[], bool], what: str) -> None:
    """Wait until ``done()`` (or fail after :data:`TIMEOUT_S`)."""
    deadline = time.monotonic() + TIMEOUT_S
    while not done():
        if time.monotonic() > deadline:
            raise SystemExit(f'timed out waiting for {what}')
        time.sleep(0.01)


def trace_scan(bag: Path, topic: str, scan: int, pipeline: str) -> dict[str, list[str]]:
    """Feed the first ``scan`` messages to an in-process node and trace the last one; the
    counted functions per module."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from kentreg_ros.ros.node import KentRegNode

    messages = bag_messages(bag, topic, scan)
    holder: dict[str, Any] = {}

    def is_odometry_publish(frame: FrameType) -> bool:
        return (
            frame.f_code.co_name == 'publish'
            and frame.f_locals.get('self') is holder['node']._outputs.odom
        )

    trace = PathTrace(stop_at=is_odometry_publish)
    # Before the node exists, so its worker thread starts with the profile (it records only
    # once armed); Python 3.11 has no setprofile_all_threads.
    threading.setprofile(trace.profile)
    context = Context()
    rclpy.init(context=context)
    try:
        node = KentRegNode(
            context=context,
            node_name=f'kentreg_scan_path_{uuid.uuid4().hex[:8]}',
            parameter_overrides=[Parameter('pipeline', value=pipeline)],
        )
        holder['node'] = node
        try:
            for timer in node.timers:
                timer.cancel()

            def handled() -> int:
                totals = node._counters.total
                return int(totals['published'] + totals['errors'])

            for k, msg in enumerate(messages[:-1], start=1):
                node._on_points(msg)  # one at a time: a full queue would drop the oldest
                wait_for(lambda k=k: handled() == k, f'scan {k}')  # type: ignore[misc]
            callback = threading.get_ident()
            worker = node._worker._thread.ident
            assert worker is not None
            trace.arm(callback, worker)
            sys.setprofile(trace.profile)
            node._on_points(messages[-1])
            sys.setprofile(None)
            trace.disarm_callback(callback)
            wait_for(trace.reached_publish.is_set, "the odometry publisher's publish()")
            wait_for(lambda: handled() == scan, f'scan {scan}')
        finally:
            threading.setprofile(None)
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    return {module: sorted(names) for module, names in sorted(trace.functions.items())}


def render(functions: dict[str, list[str]]) -> str:
    """The table: functions per module and the total."""
    width = max(len(m) for m in functions)
    lines = [f'{m:<{width}}  {len(f):3d}  {", ".join(f)}' for m, f in functions.items()]
    total = sum(len(f) for f in functions.values())
    lines.append(f'{"total":<{width}}  {total:3d}  in {len(functions)} modules')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--bag', type=Path, default=REPO / 'bags' / 'balm_50')
    parser.add_argument('--topic', default='/points')
    parser.add_argument('--scan', type=int, default=4, help='which scan to trace (1-based)')
    parser.add_argument('--pipeline', choices=('sequential', 'process'), default='sequential')
    parser.add_argument('--json', type=Path, help='write the counts here')
    options = parser.parse_args(argv)
    if options.scan < 1:
        parser.error('--scan counts from 1')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault(
        'FASTRTPS_DEFAULT_PROFILES_FILE', str(REPO / 'test' / 'fastdds_localhost.xml')
    )
    functions = trace_scan(options.bag, options.topic, options.scan, options.pipeline)
    print(render(functions))
    if options.json is not None:
        total = sum(len(f) for f in functions.values())
        doc = {'bag': str(options.bag), 'scan': options.scan, 'pipeline': options.pipeline,
               'total': total, 'modules': len(functions), 'functions': functions}  # fmt: skip
        options.json.write_text(json.dumps(doc, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
