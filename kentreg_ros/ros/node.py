"""``kentreg_node``: live LiDAR odometry from ``sensor_msgs/PointCloud2`` with rclpy.

Topics (relative names, remap as usual: ``--ros-args -r points:=/velodyne_points``; outputs
under one prefix, :mod:`kentreg_ros.io.names`, so none collides with a robot's ``/odom``):

============================ ===================================== ==============================
``points``                   sensor_msgs/PointCloud2 (subscribed)  sensor-data QoS by default
``initialpose``              PoseWithCovarianceStamped (subscr.)   sets the pose (map: a search)
``kentreg/odometry``         nav_msgs/Odometry                     odom -> moving frame, twist
``kentreg/pose``             geometry_msgs/PoseStamped             the same pose
``kentreg/path``             nav_msgs/Path                         the last ``path_length`` poses
``kentreg/cloud_registered`` sensor_msgs/PointCloud2               each scan's registered points
``kentreg/map``              sensor_msgs/PointCloud2               around the sensor, latched
``/diagnostics``             diagnostic_msgs/DiagnosticArray       rates, latency, drops, mode
``/tf``, ``/tf_static``      odom -> moving frame, base <- sensor  when tf2_ros is installed
``~/save_map``               std_srvs/Trigger (service)            writes map.ply + TUM poses
``~/reset``                  std_srvs/Trigger (service)            restart the trajectory
``~/pose``                   PoseWithCovarianceStamped             map: the pose in ``map_frame``
``~/state``                  std_msgs/String (latched)             map: searching, localized, ...
``~/relocalize``             std_srvs/Trigger (service)            map: search from no start
============================ ===================================== ==============================

With a ``map_file`` (localization mode, :mod:`kentreg_ros.ros.localization`) the node also places
the odometry's scans in that saved map, in a thread of its own, and sends ``map_frame ->
odom_frame`` on /tf (REP-105) once it has; ``initialpose`` then is the moving frame's pose in
``map_frame``, and its covariance bounds the search.

The moving frame is ``base_frame``, or the cloud's own frame when it is empty (the default);
frames and TF are :mod:`kentreg_ros.ros.frames`, the outputs and the map of the run
:mod:`kentreg_ros.ros.outputs`, the services :mod:`kentreg_ros.ros.services`, the parameters
(flat names, :data:`kentreg_ros.io.params.PARAMETERS`) :mod:`kentreg_ros.ros.parameters`,
diagnostics :mod:`kentreg_ros.ros.diagnostics`. ``qos_overrides.<topic>.<publisher|
subscription>.{history,depth,reliability}`` apply to the input and every output topic.

Threading: the subscription callback only decodes the message (numpy views of its buffer) and
hands the scan to the worker (:class:`~kentreg_ros.ros.worker.ScanWorker`): a bounded queue
and one thread that runs :class:`~kentreg_ros.core.Odometry` and publishes. The worker owns
what happens to a scan: drops (counted and reported in ``diagnostics``), parameter changes and
resets applied between scans, stamps and frames that do not continue the trajectory,
unexpected errors. This module is the ROS wiring around it: parameters, endpoints, callbacks,
services, timers, diagnostics and the node's life.

Logging: from start-up to :meth:`KentRegNode.destroy_node` the records of the package's Python
loggers (the core's rejected scans and fall-backs, deskewing without per-point times) go to the
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

import sys
import time
from pathlib import Path
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
from kentreg_ros.core import InThreadPreparer, Odometry, Preparer
from kentreg_ros.io import names
from kentreg_ros.io.livox import is_custom_msg, live_custom_msg_hint
from kentreg_ros.io.params import NODE_NAME, NodeSettings, PipelineMode
from kentreg_ros.io.pointcloud2 import pointcloud2_to_array
from kentreg_ros.io.pointtimes import POINT_TIME_FIELDS, point_time_field
from kentreg_ros.ros import parameters, services
from kentreg_ros.ros.diagnostics import Counters, localization_status, odometry_status
from kentreg_ros.ros.frames import Frames
from kentreg_ros.ros.localization import KeepingPreparer, LocalizationWorker, map_path
from kentreg_ros.ros.logbridge import RclpyLogHandler
from kentreg_ros.ros.outputs import (
    MAP_TICK_S,
    Outputs,
    input_qos,
    qos_overridable,
    qos_override_errors,
)
from kentreg_ros.ros.parameters import ParameterError, StartupError
from kentreg_ros.ros.usage import build_parser
from kentreg_ros.ros.worker import ODOMETRY_HISTORY, THROTTLE_S, QueuedScan, ScanWorker
from kentreg_ros.runtime import ProcessPreparer

__all__ = ['KentRegNode', 'StartupError', 'main']

POINTCLOUD2_TYPE = 'sensor_msgs/msg/PointCloud2'


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
        # The core's warnings (rejected scans, deskew without times, fall-backs) reach this
        # node's logger, and so /rosout, from now until destroy_node.
        self._log_handler = RclpyLogHandler(self.get_logger(), throttle_s=THROTTLE_S).attach()
        self._counters = Counters()
        try:
            declared = parameters.declare(self)
            path = map_path(declared.node)  # a map_file that is no map stops the node now
        except StartupError:
            self._log_handler.detach()
            super().destroy_node()
            raise
        self._config = declared.config  # the latest accepted (the worker takes it between scans)
        if declared.unknown:
            self.get_logger().warning(
                f'Ignoring parameter(s) {list(declared.unknown)}: not parameters of this node '
                '(see the parameter table in docs/configuration.md; research settings such '
                'as em.* are set from Python or the command lines).'
            )

        self._last_received = time.monotonic()
        self._window_start = time.monotonic()
        #: Message types other than PointCloud2 seen on the input topic (each said once).
        self._foreign_input_types: set[str] = set()

        # The odometry (and where it prepares the scans) before the publishers and
        # subscriptions: it loads the compiled kernels (numba), which, loaded after them, left
        # the node to crash (SIGSEGV) when Ctrl-C came again while it shut down (test_node).
        # pipeline: process prepares the scans ahead in a worker process; sequential, in the
        # odometry's thread when it steps (nothing to hand over, take back or stop).
        process = declared.node.pipeline == PipelineMode.PROCESS
        ahead = ProcessPreparer() if process else None
        preparer: Preparer = ahead if ahead is not None else InThreadPreparer()
        # With a map, the localization places the scans as the odometry prepared them.
        keeper = KeepingPreparer(preparer) if path is not None else None
        odometry = Odometry(
            self._config, max_history=ODOMETRY_HISTORY, preparer=keeper or preparer
        )
        try:
            self._create_endpoints(declared.node, tf)
            self._localization = self._create_localization(path, declared.node, keeper)
        except StartupError:
            if ahead is not None:
                ahead.close()
            self._log_handler.detach()
            super().destroy_node()
            raise
        self._worker = ScanWorker(
            odometry,
            ahead,
            declared.node,
            self._counters,
            self._frames,
            self._outputs,
            self.get_logger(),
            self.context.ok,
            self._localization,
        )
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._log_handler.own_thread(self._worker.start())
        if self._localization is not None:
            self._log_handler.own_thread(self._localization.start())
        child = declared.node.base_frame or "the cloud's frame"
        self.get_logger().info(
            f'kentreg_node ready: model={self._config.odometry.model}, listening on '
            f'{self._sub.topic_name}, publishing {self._outputs.odom.topic_name} in '
            f'{declared.node.odom_frame} -> {child}.'
        )

    def _create_endpoints(self, settings: NodeSettings, tf: Any) -> None:
        """Frames (``tf``: stand-ins for tf2_ros's broadcasters and buffer, see
        :class:`~kentreg_ros.ros.frames.Frames`), publishers, subscriptions, services and
        timers; ``qos_overrides.*`` apply.

        Raises
        ------
        StartupError
            A QoS override rclpy cannot apply (an unknown policy value, a wrong type).
        """
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
        self._srv_relocalize = self.create_service(Trigger, names.RELOCALIZE, self._on_relocalize)
        steady = rclpy.clock.Clock(clock_type=rclpy.clock.ClockType.STEADY_TIME)
        # Steady timers: diagnostics and the map keep coming when simulated time is paused.
        self._diag_timer = self.create_timer(
            settings.diagnostics_period, self._publish_diagnostics, clock=steady
        )
        self._map_timer = self.create_timer(MAP_TICK_S, self._publish_map_and_path, clock=steady)

    def _create_localization(
        self, path: Path | None, settings: NodeSettings, keeper: KeepingPreparer | None
    ) -> LocalizationWorker | None:
        """The localization in the map at ``path`` (None without one): its publishers now, its
        thread (which loads the map) when the node starts."""
        if path is None or keeper is None:
            return None
        with qos_override_errors():
            return LocalizationWorker(
                self, path, settings, self._config, self._frames, keeper, self.get_logger(),
                self.context.ok,
            )  # fmt: skip

    # ----------------------------------------------------------------------------------------
    # Parameters

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        try:
            changed = parameters.changes(params, self._config, self._worker.settings)
        except ParameterError as exc:
            self.get_logger().warning(f'Rejected parameter change: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        config = changed.config if changed.config != self._config else None
        settings = changed.node if changed.node != self._worker.settings else None
        self._config = changed.config
        self._worker.change(config, settings)
        self.get_logger().info(f'Parameters changed: {parameters.values_text(params)}')
        return SetParametersResult(successful=True)

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
        scan = QueuedScan(
            points=cloud.points,
            stamp_ns=cloud.stamp_ns,  # type: ignore[arg-type]  # a PointCloud2 has a stamp
            frame_id=cloud.frame_id or '',
            received=received,
            point_times=point_time_field(cloud.extras),
        )
        self._worker.put(scan)

    def _on_reset(self, request: Any, response: Any) -> Any:
        self._worker.request_reset()
        response.success = True
        response.message = 'The trajectory restarts at the next scan.'
        self.get_logger().info('Reset requested: the trajectory restarts at the next scan.')
        return response

    def _on_save_map(self, request: Any, response: Any) -> Any:
        settings = self._worker.settings
        response.success, response.message, _ = services.save_map(self._outputs, settings)
        if response.success:  # rclpy's logger wants one severity per call site
            self.get_logger().info(f'~/save_map: {response.message}')
        else:
            self.get_logger().warning(f'~/save_map: {response.message}')
        return response

    def _on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        settings = self._worker.settings
        if self._localization is not None:
            self._on_initial_pose_in_map(msg, self._localization, settings)
            return
        T = services.initial_pose(msg, settings, self._frames)
        if isinstance(T, str):
            self.get_logger().warning(f'Ignored an initialpose message: {T}.')
            return
        self._outputs.request_pose(T)
        self.get_logger().info(
            f'Initial pose set: the moving frame at {np.round(T[:3, 3], 3).tolist()} m in '
            f'{settings.odom_frame} from the next scan on.'
        )

    def _on_initial_pose_in_map(
        self, msg: PoseWithCovarianceStamped, localization: LocalizationWorker, settings: Any
    ) -> None:
        """Localization mode: ``initialpose`` is the moving frame in ``map_frame``, and its
        covariance the window of the map search (:func:`~kentreg_ros.ros.services.
        search_window`); the odometry is left alone."""
        T = services.initial_pose(msg, settings, self._frames, fixed=settings.map_frame)
        window = services.search_window(msg.pose.covariance)
        if isinstance(T, str) or isinstance(window, str):
            self.get_logger().warning(f'Ignored an initialpose message: {T or window}.')
            return
        localization.set_initial_pose(T, window)
        self.get_logger().info(
            f'Initial pose in {settings.map_frame}: the moving frame at '
            f'{np.round(T[:3, 3], 2).tolist()} m; searching the map within '
            f'{window.distance:.2f} m and {window.angle_deg:.0f} deg of it from the next scan on.'
        )

    def _on_relocalize(self, request: Any, response: Any) -> Any:
        if self._localization is None:
            response.success = False
            response.message = 'No map_file: this node runs odometry only, with nothing to search.'
        else:
            response.success, response.message = self._localization.relocalize()
        if response.success:  # rclpy's logger wants one severity per call site
            self.get_logger().info(f'~/relocalize: {response.message}')
        else:
            self.get_logger().warning(f'~/relocalize: {response.message}')
        return response

    def _publish_map_and_path(self) -> None:
        settings = self._worker.settings
        self._outputs.publish_map(settings)
        self._outputs.publish_path(settings)

    # ----------------------------------------------------------------------------------------
    # Diagnostics (executor thread)

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        period = max(now - self._window_start, 1e-6)
        self._window_start = now
        total, window = self._counters.take_window()
        if not total['received']:
            self.check_input_type()
        snap = self._worker.snapshot(window['published'], window['processed'])
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
        if self._localization is not None:
            msg.status.append(localization_status(self.get_name(), self._localization.snapshot()))
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
        stopped = self._worker.stop(self.WORKER_STOP_TIMEOUT_S)
        if self._localization is not None:
            stopped &= self._localization.stop(self.WORKER_STOP_TIMEOUT_S)
        self._log_handler.detach()
        if not stopped:
            self.get_logger().error(
                f'The worker did not stop within {self.WORKER_STOP_TIMEOUT_S:g} s (a scan still '
                'in hand); leaving its publishers in place and destroying only the input side.'
            )
            for sub in (self._sub, self._sub_pose):
                self.destroy_subscription(sub)
            for srv in (self._srv_reset, self._srv_save, self._srv_relocalize):
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
