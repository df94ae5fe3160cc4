"""``kentreg_node``: live LiDAR odometry from ``sensor_msgs/PointCloud2`` with rclpy.

Topics (relative names, remap as usual: ``--ros-args -r points:=/velodyne_points``; outputs
under one prefix, :mod:`kentreg_ros.io.names`, so none collides with a robot's ``/odom``):

============================ ===================================== ==============================
``points``                   sensor_msgs/PointCloud2 (subscribed)  sensor-data QoS by default
``initialpose``              PoseWithCovarianceStamped (subscr.)   sets the current pose (RViz)
``kentreg/odometry``         nav_msgs/Odometry                     odom -> moving frame, twist
``kentreg/pose``             geometry_msgs/PoseStamped             the same pose
``kentreg/path``             nav_msgs/Path                         the last ``path_length`` poses
``kentreg/cloud_registered`` sensor_msgs/PointCloud2               each scan's registered points
``kentreg/map``              sensor_msgs/PointCloud2               around the sensor, latched
``/diagnostics``             diagnostic_msgs/DiagnosticArray       rates, latency, drops, mode
``/tf``, ``/tf_static``      odom -> moving frame, base <- sensor  when tf2_ros is installed
``~/save_map``               std_srvs/Trigger (service)            writes map.ply + TUM poses
``~/reset``                  std_srvs/Trigger (service)            restart the trajectory
============================ ===================================== ==============================

The moving frame is ``base_frame``, or the cloud's own frame when it is empty (the default);
frames and TF are :mod:`kentreg_ros.ros.frames`, the outputs and the map of the run
:mod:`kentreg_ros.ros.outputs`, the services :mod:`kentreg_ros.ros.services`, the parameters
(flat names, :data:`kentreg_ros.io.params.PARAMETERS`) :mod:`kentreg_ros.ros.parameters`,
diagnostics :mod:`kentreg_ros.ros.diagnostics`. ``qos_overrides.<topic>.<publisher|
subscription>.{history,depth,reliability}`` apply to the input and every output topic.

Threading: the subscription callback only decodes the message (numpy views of its buffer) and
puts the scan into a bounded queue; one worker thread runs
:class:`~kentreg_ros.core.odometry.Odometry` and publishes. When the queue is full the oldest
scan is dropped by default ("latest wins"), so the odometry never lags the sensor; every drop
is counted and reported in ``diagnostics``. Parameter changes and resets are handed to the
worker and applied between scans. An unexpected error while the worker handles a scan (a bug)
skips that scan, counts it and logs its traceback once per kind of error; the trajectory goes
on, and restarts only after :data:`MAX_ERRORS_IN_A_ROW` errors in a row.

Logging: from start-up to :meth:`KentRegNode.destroy_node` the records of the package's Python
loggers (the core's rejected scans, deskewing without per-point times, frame changes) go to the
node's rclpy logger, so to ``/rosout``, throttled per kind of message
(:class:`~kentreg_ros.ros.logbridge.RclpyLogHandler`).

Input of another type: DDS never delivers a message whose type differs from the subscription's,
and says nothing. While no scan has come, the node looks at the publishers of its input topic
every diagnostics period and logs an error once per other type it finds, with what to do for a
Livox ``CustomMsg`` (:func:`~kentreg_ros.io.livox.live_custom_msg_hint`).

Every output carries the stamp of the scan it was computed from. A stamp that goes backwards
(a bag played again, a sensor restart) or a change of the sensor frame restarts the trajectory
with a warning instead of corrupting it; a repeated stamp is dropped and counted.
"""

from __future__ import annotations

import collections
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
import rclpy.clock
import rclpy.logging
import rclpy.time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from kentreg_ros.cli.common import (
    EXIT_BAD_INPUT,
    CliError,
    interrupt_through_rclpy,
)
from kentreg_ros.core import KentRegConfig, PointTimes
from kentreg_ros.io import names
from kentreg_ros.io.livox import is_custom_msg, live_custom_msg_hint
from kentreg_ros.io.params import NODE_NAME, NodeSettings
from kentreg_ros.io.pointcloud2 import POINT_TIME_FIELDS, point_time_field, pointcloud2_to_array
from kentreg_ros.ros import parameters, services
from kentreg_ros.ros.diagnostics import Counters, Snapshot, odometry_status
from kentreg_ros.ros.frames import Frames, moving_frame
from kentreg_ros.ros.logbridge import RclpyLogHandler
from kentreg_ros.ros.outputs import (
    MAP_TICK_S,
    Outputs,
    input_qos,
    qos_overridable,
    qos_override_errors,
)
from kentreg_ros.ros.parameters import ParameterError, StartupError
from kentreg_ros.ros.pipeline import close_odometry, create_odometry, discard, prefetch
from kentreg_ros.ros.usage import build_parser

__all__ = ['KentRegNode', 'StartupError', 'main']

FloatArray = np.ndarray
POINTCLOUD2_TYPE = 'sensor_msgs/msg/PointCloud2'
#: Poses the odometry keeps (the prediction needs two); the path keeps its own bounded history.
ODOMETRY_HISTORY = 4
#: Seconds between repeated warnings of the same kind (malformed input, drops, the core's).
THROTTLE_S = 5.0
#: Unexpected worker errors in a row after which the trajectory restarts. One error costs one
#: scan (skipped; the pose goes on from the scans before, and odom must not jump, REP-105). But
#: errors that keep coming on scan after scan point at the odometry's own state (a model or a
#: velocity left broken), which only a restart clears; three in a row tells that apart from
#: two unrelated odd scans, and costs a 10 Hz sensor 0.3 s of odometry.
MAX_ERRORS_IN_A_ROW = 3
#: Kinds of unexpected error whose traceback is logged in full (each once); later kinds get the
#: one-line message only, so a node failing in ever new ways cannot fill its log.
MAX_ERROR_KINDS = 32


@dataclass
class _Scan:
    points: np.ndarray
    stamp_ns: int
    frame_id: str
    received: float  # time.monotonic()
    n_nonfinite: int
    point_times: PointTimes | None = None  # the driver's per-point times, for deskewing


class KentRegNode(Node):
    """LiDAR odometry node; see the module docstring for topics and behaviour.

    Raises
    ------
    StartupError
        A parameter (from a parameter file or ``-p``) is of the wrong type, out of range, not
        among its choices, unknown, or inconsistent with another.
    """

    #: How long :meth:`destroy_node` waits for the worker to finish the scan in hand (s).
    WORKER_STOP_TIMEOUT_S = 10.0

    def __init__(self, *, node_name: str = NODE_NAME, tf: Any = None, **kwargs: Any) -> None:
        # rclpy declares every parameter given for this node (files, -p, parameter_overrides)
        # before __init__ returns, so the node can see what it was given through the public
        # parameter API, validate it and warn about names it does not know (parameters.declare).
        super().__init__(node_name, automatically_declare_parameters_from_overrides=True, **kwargs)
        # The core's warnings (rejected scans, deskew without times, frame changes) reach this
        # node's logger, and so /rosout, from now until destroy_node.
        self._log_handler = RclpyLogHandler(self.get_logger(), throttle_s=THROTTLE_S).attach()
        self._counters = Counters()
        try:
            declared = parameters.declare(self)
        except StartupError:
            self._log_handler.detach()
            super().destroy_node()
            raise
        self._config, self._settings = declared.config, declared.node
        if declared.unknown:
            self.get_logger().warning(
                f'Ignoring parameter(s) {list(declared.unknown)}: not parameters of this node '
                '(see the README parameter table; research settings such as em.* are set from '
                'Python or the command lines).'
            )

        self._lock = threading.Condition()
        self._queue: collections.deque[_Scan] = collections.deque()
        self._pending_config: KentRegConfig | None = None
        #: The model the worker registers against (changed by the worker, under the lock, when
        #: it adopts a pending configuration); self._config is the latest accepted one.
        self._model_in_use = self._config.odometry.model
        self._pending_reset = False
        self._stop = False

        # Worker state: only the worker thread reads or writes these after start-up. Changes
        # from the executor thread (parameters, reset) reach it under the lock as pending
        # values or through the settings it copies before each scan.
        self._odometry = create_odometry(self._config, self._settings, ODOMETRY_HISTORY)
        self._frame_id: str | None = None
        self._last_stamp_ns: int | None = None  # of the last scan taken (duplicates, going back)
        self._last_stepped_ns: int | None = None  # of the last scan the odometry stepped with
        self._last_health = ''
        self._last_message = ''
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=1000)
        self._step_ms: collections.deque[float] = collections.deque(maxlen=1000)
        self._last_received = time.monotonic()
        self._window_start = time.monotonic()
        self._errors_in_a_row = 0
        #: Kinds of unexpected error (type, file, line) whose traceback was logged.
        self._error_kinds: set[tuple[str, str, int]] = set()
        #: Message types other than PointCloud2 seen on the input topic (each said once).
        self._foreign_input_types: set[str] = set()

        try:
            self._create_endpoints(tf)
        except StartupError:
            self._log_handler.detach()
            super().destroy_node()
            raise
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._worker = threading.Thread(target=self._run_worker, name='kentreg_worker')
        self._worker.daemon = True
        self._worker.start()
        self._log_handler.own_thread(self._worker.ident)
        child = self._settings.base_frame or "the cloud's frame"
        self.get_logger().info(
            f'kentreg_node ready: model={self._config.odometry.model}, listening on '
            f'{self._sub.topic_name}, publishing {self._outputs.odom.topic_name} in '
            f'{self._settings.odom_frame} -> {child}.'
        )

    def _create_endpoints(self, tf: Any) -> None:
        """Frames (``tf``: stand-ins for tf2_ros's broadcasters and buffer, see
        :class:`~kentreg_ros.ros.frames.Frames`), publishers, subscriptions, services and
        timers; ``qos_overrides.*`` apply.

        Raises
        ------
        StartupError
            A QoS override rclpy cannot apply (an unknown policy value, a wrong type).
        """
        settings = self._settings
        with qos_override_errors():
            self._frames = Frames(self, settings, tf)
            self._outputs = Outputs(self, self._frames, settings)
            self._pub_diag = self.create_publisher(
                DiagnosticArray, names.DIAGNOSTICS, 10, qos_overriding_options=qos_overridable()
            )
            self._sub = self.create_subscription(
                PointCloud2,
                names.POINTS,
                self._on_points,
                input_qos(settings),
                qos_overriding_options=qos_overridable(),
            )
        self._sub_pose = self.create_subscription(
            PoseWithCovarianceStamped, names.INITIAL_POSE, self._on_initial_pose, 10
        )
        self._srv_reset = self.create_service(Trigger, '~/reset', self._on_reset)
        self._srv_save = self.create_service(Trigger, '~/save_map', self._on_save_map)
        steady = rclpy.clock.Clock(clock_type=rclpy.clock.ClockType.STEADY_TIME)
        # Steady timers: diagnostics and the map keep coming when simulated time is paused.
        self._diag_timer = self.create_timer(
            settings.diagnostics_period, self._publish_diagnostics, clock=steady
        )
        self._map_timer = self.create_timer(MAP_TICK_S, self._publish_map_and_path, clock=steady)

    # ----------------------------------------------------------------------------------------
    # Parameters

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            changed = parameters.changes(params, self._config, self._settings)
        except ParameterError as exc:
            self.get_logger().warning(f'Rejected parameter change: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        with self._lock:
            if changed.config != self._config:
                self._config = changed.config
                self._pending_config = changed.config
            if changed.node != self._settings:
                self._apply_settings(changed.node)
        self.get_logger().info(f'Parameters changed: {parameters.values_text(params)}')
        return SetParametersResult(successful=True)

    def _apply_settings(self, settings: NodeSettings) -> None:
        """Adopt new runtime node settings (called with the lock held)."""
        old = self._settings
        self._settings = settings  # path_length reaches the worker's path through it
        if settings.base_to_lidar != old.base_to_lidar or (
            settings.odom_frame,
            settings.base_frame,
        ) != (old.odom_frame, old.base_frame):
            self._pending_reset = True  # the published frame changed: start a new trajectory
        while len(self._queue) > settings.queue_size:
            self._queue.popleft()
            self._counters.add('dropped_queue')

    # ----------------------------------------------------------------------------------------
    # Input (executor thread)

    def _on_points(self, msg: PointCloud2) -> None:
        received = time.monotonic()
        self._last_received = received
        self._counters.add('received')
        try:
            # Only a per-point time field is decoded besides x, y, z: it feeds the deskewing.
            names = {f.name for f in msg.fields}
            cloud = pointcloud2_to_array(
                msg, fields=[n for n in POINT_TIME_FIELDS if n in names][:1]
            )
        except Exception as exc:
            # Broad on purpose: whatever a malformed message makes the decoder raise (its
            # documented InvalidPointCloudError, or numpy's errors on an absurd layout) must
            # not leave this callback: an exception here propagates out of spin() and stops
            # the node.
            self._counters.add('malformed')
            self.get_logger().warning(
                f'Skipped a malformed PointCloud2: {exc}', throttle_duration_sec=THROTTLE_S
            )
            return
        if cloud.n_dropped:
            self._counters.add('nonfinite_points', cloud.n_dropped)
        scan = _Scan(
            points=cloud.points,
            stamp_ns=cloud.stamp_ns,  # type: ignore[arg-type]  # a PointCloud2 has a stamp
            frame_id=cloud.frame_id or '',
            received=received,
            n_nonfinite=cloud.n_dropped,
            point_times=point_time_field(cloud.extras),
        )
        prefetch(self._odometry, scan.points, scan.stamp_ns, scan.point_times)
        with self._lock:
            if len(self._queue) >= self._settings.queue_size:
                self._counters.add('dropped_queue')  # the oldest: latest wins
                discard(self._odometry, self._queue.popleft().points)
            self._queue.append(scan)
            self._lock.notify()

    def _on_reset(self, request: Any, response: Any) -> Any:
        with self._lock:
            self._pending_reset = True
            self._lock.notify()
        response.success = True
        response.message = 'The trajectory restarts at the next scan.'
        self.get_logger().info('Reset requested: the trajectory restarts at the next scan.')
        return response

    def _on_save_map(self, request: Any, response: Any) -> Any:
        with self._lock:
            settings = self._settings
        response.success, response.message, _ = services.save_map(self._outputs, settings)
        if response.success:  # rclpy's logger wants one severity per call site
            self.get_logger().info(f'~/save_map: {response.message}')
        else:
            self.get_logger().warning(f'~/save_map: {response.message}')
        return response

    def _on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        with self._lock:
            settings = self._settings
        T = services.initial_pose(msg, settings, self._frames)
        if isinstance(T, str):
            self.get_logger().warning(f'Ignored an initialpose message: {T}.')
            return
        self._outputs.request_pose(T)
        self.get_logger().info(
            f'Initial pose set: the moving frame at {np.round(T[:3, 3], 3).tolist()} m in '
            f'{settings.odom_frame} from the next scan on.'
        )

    def _publish_map_and_path(self) -> None:
        with self._lock:
            settings = self._settings
        self._outputs.publish_map(settings)
        self._outputs.publish_path(settings)

    # ----------------------------------------------------------------------------------------
    # Worker thread

    def _run_worker(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._stop:
                    self._lock.wait(timeout=0.5)
                if self._stop:
                    return
                scan = self._queue.popleft()
                config, self._pending_config = self._pending_config, None
                reset, self._pending_reset = self._pending_reset, False
                settings = self._settings
            try:
                if config is not None:
                    self._odometry.reconfigure(config)
                    with self._lock:
                        self._model_in_use = config.odometry.model
                if reset:
                    self._reset('reset requested')
                self._process(scan, settings)
            except Exception as exc:
                if not self.context.ok():
                    # Ctrl-C (or an external shutdown) took the ROS context down under the scan
                    # in hand, so its outputs could not go out: the end of the node, not an
                    # error of the scan. Nothing more can be published; the worker stops.
                    return
                # Broad on purpose: an exception would end this thread silently, leaving a node
                # that still subscribes and reports but never publishes odometry again.
                self._on_worker_error(exc, scan)
            else:
                self._errors_in_a_row = 0

    def _on_worker_error(self, exc: Exception, scan: _Scan) -> None:
        """Count an unexpected error, skip its scan and keep the trajectory (REP-105: ``odom``
        must not jump); log the traceback once per kind of error; restart the trajectory only
        after :data:`MAX_ERRORS_IN_A_ROW` in a row."""
        self._counters.add('errors')
        self._errors_in_a_row += 1
        log = self.get_logger()
        text = f'{type(exc).__name__}: {exc}'
        # The kind of an error: its type and the line that raised it.
        frames = traceback.extract_tb(exc.__traceback__)
        where = (frames[-1].filename, frames[-1].lineno or 0) if frames else ('', 0)
        kind = (type(exc).__qualname__, *where)
        skipped = (
            f'Unexpected error on the scan stamped {scan.stamp_ns * 1e-9:.3f} s ({text}): the '
            'scan is skipped (diagnostics count it in errors), the trajectory goes on.'
        )
        if kind not in self._error_kinds and len(self._error_kinds) < MAX_ERROR_KINDS:
            self._error_kinds.add(kind)
            trace = ''.join(traceback.format_exception(exc)).rstrip()
            log.error(f'{skipped} Its traceback (shown once for this kind of error):\n{trace}')
        else:
            log.error(skipped, throttle_duration_sec=THROTTLE_S)
        if self._errors_in_a_row >= MAX_ERRORS_IN_A_ROW:
            log.error(
                f'{self._errors_in_a_row} unexpected errors in a row: the odometry state is '
                'taken to be broken, so the trajectory restarts (odom starts again at the '
                'identity).'
            )
            self._errors_in_a_row = 0
            self._reset(f'{MAX_ERRORS_IN_A_ROW} unexpected errors in a row')

    def _reset(self, why: str) -> None:
        self._odometry.reset()
        self._outputs.reset()
        self._frames.reset()
        with self._lock:
            self._frame_id = None
        self._last_stamp_ns = None
        self._last_stepped_ns = None
        self._counters.add('resets')
        self.get_logger().info(f'Trajectory restarted ({why}).')

    def _process(self, scan: _Scan, settings: NodeSettings) -> None:
        log = self.get_logger()
        if self._frame_id is not None and scan.frame_id != self._frame_id:
            log.warning(
                f'The sensor frame changed from {self._frame_id!r} to {scan.frame_id!r}: '
                'restarting the trajectory.'
            )
            self._reset('sensor frame changed')
        if self._last_stamp_ns is not None:
            if scan.stamp_ns == self._last_stamp_ns:
                self._counters.add('dropped_duplicate_stamp')
                log.warning(
                    'Dropped a scan with the same stamp as the previous one.',
                    throttle_duration_sec=THROTTLE_S,
                )
                return
            if scan.stamp_ns < self._last_stamp_ns:
                log.warning(
                    f'Time went backwards by {(self._last_stamp_ns - scan.stamp_ns) * 1e-9:.3f} s '
                    '(bag replayed? sensor restarted?): restarting the trajectory.'
                )
                self._reset('time went backwards')
        T_moving_lidar = self._frames.mount(scan.frame_id, settings, time.monotonic())
        if T_moving_lidar is None:
            self._counters.add('dropped_waiting_for_tf')
            return
        with self._lock:
            self._frame_id = scan.frame_id
        self._last_stamp_ns = scan.stamp_ns

        step = self._odometry.step(
            scan.points, scan.stamp_ns, frame_id=scan.frame_id, point_times=scan.point_times
        )
        # The twist spans the odometry's own last step: after a scan skipped by an error the
        # scan before it, not the skipped one.
        prev_stamp, self._last_stepped_ns = self._last_stepped_ns, scan.stamp_ns
        self._counters.add('processed')
        self._counters.add(step.health)
        if step.searched:
            self._counters.add('searched')
        child = moving_frame(scan.frame_id, settings)
        self._outputs.publish(step, T_moving_lidar, prev_stamp, settings, child)
        self._counters.add('published')
        latency_ms = (time.monotonic() - scan.received) * 1e3
        with self._lock:  # read by the diagnostics timer on the executor thread
            self._last_health, self._last_message = step.health, step.message
            self._latencies_ms.append(latency_ms)
            self._step_ms.append(step.timings.get('total', 0.0))

    # ----------------------------------------------------------------------------------------
    # Diagnostics (executor thread)

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        period = max(now - self._window_start, 1e-6)
        self._window_start = now
        total, window = self._counters.take_window()
        if not total['received']:
            self.check_input_type()
        with self._lock:  # everything the worker writes is read under the lock
            pending = self._pending_config
            snap = Snapshot(
                queued=len(self._queue),
                model=str(self._model_in_use),
                pending_model=str(pending.odometry.model) if pending is not None else '',
                latencies_ms=list(self._latencies_ms)[-max(window['published'], 1) :],
                steps_ms=list(self._step_ms)[-max(window['processed'], 1) :],
                frame_id=self._frame_id or '',
                last_health=str(self._last_health),
                last_message=self._last_message,
            )
        status = odometry_status(
            self.get_name(),
            self._sub.topic_name,
            total,
            window,
            period,
            now - self._last_received,
            snap,
        )
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [status]
        self._pub_diag.publish(msg)

    def check_input_type(self) -> list[str]:
        """Log an error for each message type other than PointCloud2 that a publisher of the
        input topic offers and that was not said before; return those messages."""
        topic = self._sub.topic_name
        try:
            offered = {info.topic_type for info in self.get_publishers_info_by_topic(topic)}
        except Exception:  # a graph query racing the node's shutdown; the next period retries
            return []
        said = []
        for msgtype in sorted(offered - self._foreign_input_types - {POINTCLOUD2_TYPE}):
            self._foreign_input_types.add(msgtype)
            if is_custom_msg(msgtype):
                text = live_custom_msg_hint(topic, msgtype)
            else:
                text = (
                    f'{topic} carries {msgtype}, not {POINTCLOUD2_TYPE}: no message of it '
                    'reaches this node. Remap points to a PointCloud2 topic.'
                )
            self.get_logger().error(text)
            said.append(text)
        return said

    # ----------------------------------------------------------------------------------------
    # Lifecycle

    def destroy_node(self) -> None:
        """Stop and join the worker (it finishes the scan in hand), then destroy the node.

        When the worker has not stopped within :attr:`WORKER_STOP_TIMEOUT_S` (a registration
        still running), only the input side is destroyed (subscriptions, services, timers)
        and the reason is logged: the publishers and tf objects stay, since the worker may
        still publish with them. It stops after that scan; its thread is a
        daemon, so it does not keep the process alive.
        """
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self._worker.join(timeout=self.WORKER_STOP_TIMEOUT_S)
        close_odometry(self._odometry, self._worker)
        self._log_handler.detach()
        if self._worker.is_alive():
            self.get_logger().error(
                f'The worker did not stop within {self.WORKER_STOP_TIMEOUT_S:g} s (a scan still '
                'in hand); leaving its publishers in place and destroying only the input side.'
            )
            for sub in (self._sub, self._sub_pose):
                self.destroy_subscription(sub)
            for srv in (self._srv_reset, self._srv_save):
                self.destroy_service(srv)
            for timer in (self._diag_timer, self._map_timer):
                self.destroy_timer(timer)
            return
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``kentreg_node`` / ``ros2 run kentreg_ros kentreg_node``.

    Parameters
    ----------
    args : list of str, optional
        The whole command line, program name first, as ``rclpy.init`` takes it (default
        ``sys.argv``).

    Returns 0 on a clean shutdown, 1 when the ROS arguments or the parameters are invalid (the
    reason is logged, in one line) and 2 on an argument before ``--ros-args`` that is not the
    node's own (one line naming it). ``--help`` and ``--version`` print and exit 0 without
    initialising ROS.
    """
    argv = list(sys.argv if args is None else args)
    try:
        own = remove_ros_args(argv)[1:]
    except RuntimeError as exc:  # rcl's RCLInvalidROSArgsError: bad --ros-args, --params-file
        print(f'{NODE_NAME}: cannot start: {exc}', file=sys.stderr)
        return 1
    try:
        unknown = build_parser().parse_known_args(own)[1]
        if unknown:
            raise CliError(
                f'unrecognized arguments: {" ".join(unknown)} (ROS arguments go after '
                f'--ros-args: {NODE_NAME} --ros-args -p name:=value --params-file FILE)'
            )
    except CliError as exc:
        print(f'{NODE_NAME}: error: {exc}', file=sys.stderr)
        return EXIT_BAD_INPUT
    interrupt_through_rclpy()
    try:
        rclpy.init(args=argv)
    except RuntimeError as exc:  # rcl's RCLError: bad --ros-args, unreadable --params-file
        print(f'kentreg_node: cannot start: {exc}', file=sys.stderr)
        return 1
    node: KentRegNode | None = None
    try:
        node = KentRegNode()
        rclpy.spin(node)
    except StartupError as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f'Invalid parameters: {exc}')
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # rclpy's signal handler shuts the context down from another thread; when that lands
        # while spin() sets up its next wait, spin raises RCLError (a RuntimeError) instead of
        # ExternalShutdownException (ros2/rclpy#398). A shutdown all the same.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
