"""The node's localization mode (``map_file``): where the odometry's scans are in a saved map.

REP-105: the odometry keeps ``odom -> moving frame`` continuous; this mode adds
``map_frame -> odom_frame``, the correction of the odometry's drift that a localization in the
map finds (:class:`~kentreg_ros.core.Localizer`: a search from no start that needs
``localization.agreement`` consecutive scans to agree, then tracking from the odometry's
prediction, relocalizing when lost).

Threads. The odometry's worker must not wait for a search (about a second on one core) nor the
executor for the map's preparation (seconds for a large map), so the localization has a thread
of its own (:class:`LocalizationWorker`):

- it first loads and prepares the map (:func:`~kentreg_ros.io.mapload.load_point_map`, cached
  beside the file); the odometry runs meanwhile and the state is ``searching``;
- the odometry's worker hands it each scan it stepped (the prepared scan, reused through
  :class:`KeepingPreparer`, and its odometry pose) through a hand-over of one: a scan not taken
  before the next arrives is skipped and counted (``skipped`` in diagnostics), so the
  localization works on the newest scan, tracking (tens of milliseconds) or searching;
- the executor hands it the operator's requests (``initialpose``, ``~/relocalize``), applied
  before the next scan; the last request wins.

What goes out: ``map_frame -> odom_frame`` on /tf with every odometry step, at the scan's stamp,
from the latest placement (:meth:`LocalizationWorker.after_step`; never before the first, and
withdrawn when the odometry restarts, since the odometry frame restarts with it); ``~/pose``
(geometry_msgs/PoseWithCovarianceStamped) of each scan placed, in ``map_frame``, with the
localization's covariance; ``~/state`` (std_msgs/String, transient-local) on every change of
:class:`~kentreg_ros.core.TrackingState`. Every change of state is logged, and so is every
placement found by a search, with the size of the correction it makes: the map frame never
jumps silently (a tracked correction beyond ``localization.tracking_distance`` /
``tracking_angle_deg`` needs the gates of a search).

A ``map_file`` that does not exist or is no point-cloud file stops the node at start-up
(:func:`map_path`); a map that cannot be read or prepared (found in the background) is an ERROR
in the log and in diagnostics, and the odometry goes on without localization.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from kentreg_ros.core import (
    KentRegConfig,
    Localizer,
    OdometryStep,
    PointMap,
    Preparation,
    PreparedScan,
    PrepareInputs,
    Preparer,
    RawScan,
    TrackingState,
    TrackStep,
    Window,
    invert_transform,
    rotation_angle,
)
from kentreg_ros.io import names
from kentreg_ros.io.mapload import load_point_map
from kentreg_ros.io.params import NodeSettings
from kentreg_ros.io.scanfiles import SCAN_SUFFIXES
from kentreg_ros.ros.diagnostics import LocalizationSnapshot
from kentreg_ros.ros.frames import Frames
from kentreg_ros.ros.logbridge import UnexpectedErrors
from kentreg_ros.ros.messages import (
    covariance_to_msg,
    pose_covariance_in_base,
    pose_covariance_in_map,
    pose_to_msg,
    stamp_to_msg,
)
from kentreg_ros.ros.outputs import qos_overridable
from kentreg_ros.ros.parameters import StartupError

__all__ = ['KeepingPreparer', 'LocalizationWorker', 'MapState', 'map_path']

FloatArray = np.ndarray
#: Seconds between repeated logs of the same kind of unexpected error.
THROTTLE_S = 5.0


class MapState(StrEnum):
    """Where the map of the localization is."""

    LOADING = 'loading'
    READY = 'ready'
    FAILED = 'failed'


def map_path(settings: NodeSettings) -> Path | None:
    """The map file of ``settings`` (``~`` expanded), None without one.

    Raises
    ------
    StartupError
        ``map_file`` names no readable file, or one that is not a point cloud by its suffix.
    """
    text = settings.map_file.strip()
    if not text:
        return None
    path = Path(text).expanduser()
    if not path.is_file():
        where = '' if path.is_absolute() else f' (from {os.getcwd()})'
        raise StartupError(f'map_file {text!r}: no such file{where}.', names=('map_file',))
    if path.suffix.lower() not in SCAN_SUFFIXES:
        raise StartupError(
            f'map_file {text!r} is not a point-cloud file: expected one of '
            f'{", ".join(SCAN_SUFFIXES)}.',
            names=('map_file',),
        )
    if not os.access(path, os.R_OK):
        raise StartupError(f'map_file {text!r} cannot be read.', names=('map_file',))
    return path


class KeepingPreparer:
    """A :class:`~kentreg_ros.core.Preparer` that keeps the last scan it prepared, so that the
    localization places the odometry's own preparation (a scan is prepared once, for both).
    ``inner`` prepares; what the node hands a preparer working ahead it hands ``inner``
    itself."""

    def __init__(self, inner: Preparer) -> None:
        self.inner = inner
        self._last: tuple[int, Preparation] | None = None  # (stamp_ns, preparation)

    def prepare(self, scan: RawScan, inputs: PrepareInputs) -> Preparation:
        prep = self.inner.prepare(scan, inputs)
        self._last = (scan.stamp_ns, prep)
        return prep

    def expect(self, inputs: PrepareInputs) -> None:
        self.inner.expect(inputs)

    def prepared(self, stamp_ns: int) -> PreparedScan | None:
        """The scan stamped ``stamp_ns`` as the last preparation made it (None when the last
        preparation was another scan's, or rejected the cloud)."""
        last = self._last
        return last[1].scan if last is not None and last[0] == stamp_ns else None


@dataclass(frozen=True, eq=False)
class LocalizationInput:
    """One odometry step handed to the localization."""

    scan: PreparedScan
    T_world_lidar: FloatArray  # the odometry's pose (its world: the trajectory's first scan)
    T_moving_lidar: FloatArray  # the sensor's mount in the moving frame
    stamp_ns: int
    generation: int  # of the odometry's trajectory (a restart starts another)


@dataclass(frozen=True, eq=False)
class _Odometry:
    """The latest odometry pose when a request came."""

    generation: int
    T_world_lidar: FloatArray
    T_moving_lidar: FloatArray


@dataclass(frozen=True, eq=False)
class _InitialPose:
    """An ``initialpose``: the moving frame's pose in the map then, and the search window."""

    T_map_moving: FloatArray
    window: Window
    then: _Odometry | None

    def start(self, item: LocalizationInput) -> FloatArray:
        """``T_map_lidar`` of ``item``'s scan: the pose given, moved by the odometry's motion
        since the request (on the same trajectory)."""
        then = self.then
        if then is None or then.generation != item.generation:
            return self.T_map_moving @ item.T_moving_lidar
        T_map_lidar = self.T_map_moving @ then.T_moving_lidar
        return T_map_lidar @ invert_transform(then.T_world_lidar) @ item.T_world_lidar


_RELOCALIZE = 'relocalize'


class LocalizationWorker:
    """The localization's thread, its hand-over and its outputs (module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
        Creates ``~/pose`` and ``~/state``.
    path : Path
        The map file (:func:`map_path`).
    settings : NodeSettings
        At start-up (``map_frame`` is read-only).
    config : KentRegConfig
        The localization's configuration (``localization.*``, the search's).
    frames : Frames
        Sends ``map_frame -> odom_frame``.
    keeper : KeepingPreparer
        The odometry's preparer, which keeps the scan it prepared last.
    log : rclpy logger
    running : callable
        Whether the node's ROS context is still up.
    load : callable, optional
        Loads the map (default :func:`~kentreg_ros.io.mapload.load_point_map`; tests hand in
        their own).
    """

    def __init__(
        self,
        node: Node,
        path: Path,
        settings: NodeSettings,
        config: KentRegConfig,
        frames: Frames,
        keeper: KeepingPreparer,
        log: Any,
        running: Callable[[], bool],
        *,
        load: Callable[..., PointMap] = load_point_map,
    ) -> None:
        self.path, self._config, self._frames, self._keeper = path, config, frames, keeper
        self._map_frame = settings.map_frame
        self._log, self._running, self._load = log, running, load
        latched = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self.pose_pub = node.create_publisher(
            PoseWithCovarianceStamped, names.LOCALIZATION_POSE, 10,
            qos_overriding_options=qos_overridable(),
        )  # fmt: skip
        self.state_pub = node.create_publisher(String, names.LOCALIZATION_STATE, latched)
        self._lock = threading.Condition()
        # Shared with the odometry's worker and the executor, under the lock.
        self._pending: LocalizationInput | None = None
        self._request: _InitialPose | str | None = None
        self._generation = 0
        self._latest: _Odometry | None = None
        self._T_map_world: tuple[int, FloatArray] | None = None  # (generation, T_map_world)
        self._stop = False
        self._map_state, self._map_message = MapState.LOADING, f'loading {path}'
        self._state = TrackingState.SEARCHING
        self._last_message, self._last_fit, self._last_ms = '', float('nan'), float('nan')
        self._counts = dict.fromkeys(
            ('updates', 'searched', 'tracked', 'misses', 'relocalizations', 'skipped', 'errors'),
            0,
        )
        self._errors = UnexpectedErrors(log, THROTTLE_S)  # only the thread's
        self._thread = threading.Thread(target=self._run, name='kentreg_localizer', daemon=True)

    # ----------------------------------------------------------------------------------------
    # From the node (executor thread) and the odometry's worker

    def start(self) -> int | None:
        """Publish the state (``searching``) and start the thread; its id."""
        self.state_pub.publish(String(data=str(self._state)))
        self._thread.start()
        return self._thread.ident

    def after_step(
        self,
        step: OdometryStep,
        T_moving_lidar: FloatArray,
        anchor: FloatArray | None,
        settings: NodeSettings,
    ) -> None:
        """The odometry's worker published ``step``: hand its scan over (when its pose came
        from a registration: a fallen-back pose is a guess to chain from) and send
        ``map_frame -> odom_frame`` at its stamp, from the latest placement (``anchor``: the
        odometry frame in the odometry's world, ``T_odom_world``)."""
        scan = self._keeper.prepared(step.stamp_ns) if step.ok else None
        with self._lock:
            generation = self._generation
            self._latest = _Odometry(generation, step.T_world_lidar, T_moving_lidar)
            if scan is not None:
                if self._pending is not None:
                    self._counts['skipped'] += 1  # the newest wins
                self._pending = LocalizationInput(
                    scan, step.T_world_lidar, T_moving_lidar, step.stamp_ns, generation
                )
                self._lock.notify_all()
            placed = self._T_map_world
        if placed is not None and placed[0] == generation and anchor is not None:
            self._frames.broadcast_map(
                step.stamp_ns, placed[1] @ invert_transform(anchor), settings
            )

    def trajectory_restarted(self) -> None:
        """The odometry restarted (its world, and so the odometry frame, starts again): the
        placement no longer holds; search again from the next scan."""
        with self._lock:
            self._generation += 1
            self._T_map_world = None
            self._pending = None
            self._latest = None
            self._lock.notify_all()

    def set_initial_pose(self, T_map_moving: FloatArray, window: Window) -> None:
        """Search within ``window`` of ``T_map_moving`` (the moving frame's pose in the map now)
        from the next scan on."""
        with self._lock:
            self._request = _InitialPose(np.array(T_map_moving, float), window, self._latest)
            self._lock.notify_all()

    def relocalize(self) -> tuple[bool, str]:
        """Search from no start from the next scan on; ``(success, message)`` for
        ``~/relocalize``."""
        with self._lock:
            if self._map_state is MapState.FAILED:
                return False, self._map_message
            self._request = _RELOCALIZE
            self._lock.notify_all()
            loading = self._map_state is MapState.LOADING
        message = 'Searching the map from no start from the next scan on.'
        return True, message + (' (The map is still loading.)' if loading else '')

    def snapshot(self) -> LocalizationSnapshot:
        """What the diagnostics report."""
        with self._lock:
            return LocalizationSnapshot(
                map_file=str(self.path),
                map_state=str(self._map_state),
                map_message=self._map_message,
                state=str(self._state),
                last_message=self._last_message,
                last_fit=self._last_fit,
                last_ms=self._last_ms,
                counts=dict(self._counts),
            )

    @property
    def state(self) -> TrackingState:
        with self._lock:
            return self._state

    @property
    def T_map_world(self) -> FloatArray | None:
        """The placement of the current trajectory (None before the first)."""
        with self._lock:
            placed = self._T_map_world
            return None if placed is None or placed[0] != self._generation else placed[1].copy()

    def stop(self, timeout: float) -> bool:
        """Stop the thread (it finishes the scan or the map in hand); True when it stopped
        within ``timeout`` s."""
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self._thread.join(timeout=timeout)
        return not self._thread.is_alive()

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    # ----------------------------------------------------------------------------------------
    # The thread

    def _run(self) -> None:
        pmap = self._load_map()
        if pmap is None:
            return
        localizer, generation = Localizer(pmap, self._config), 0
        initial: _InitialPose | None = None
        while True:
            with self._lock:
                while not (
                    self._stop
                    or self._pending is not None
                    or self._request is not None
                    or self._generation != generation
                ):
                    self._lock.wait(timeout=0.5)
                if self._stop:
                    return
                item, self._pending = self._pending, None
                request, self._request = self._request, None
                restarted, generation = self._generation != generation, self._generation
            if restarted:
                localizer = Localizer(pmap, self._config)
                self._note_state(TrackingState.SEARCHING, 'the odometry restarted')
            if request == _RELOCALIZE:
                initial = None
                localizer.relocalize()
                self._note_state(localizer.state, 'relocalization requested')
            elif isinstance(request, _InitialPose):
                initial = request
            if item is None or item.generation != generation:
                continue
            try:
                if initial is not None:
                    localizer.set_initial_pose(initial.start(item), initial.window)
                    self._note_state(localizer.state, 'initial pose given')
                    initial = None
                self._place(localizer, item)
            except Exception as exc:
                if not self._running():
                    return  # the node is going down under the scan in hand
                # Broad on purpose: an exception would end this thread silently, and the node
                # would go on without localization, saying nothing.
                self._on_error(exc, item)

    def _load_map(self) -> PointMap | None:
        t0 = time.monotonic()
        self._log.info(
            f'Loading the map {self.path} in the background: the odometry runs meanwhile, and '
            'the localization searches once it is ready.'
        )
        try:
            pmap = self._load(self.path, config=self._config)
        except Exception as exc:
            # Broad on purpose: whatever the file makes the readers raise, the operator must
            # read it, and the odometry goes on.
            message = (
                f'Cannot use map_file {str(self.path)!r}: {exc} The odometry goes on without '
                f'localization (no {self._map_frame} -> odom).'
            )
            self._log.error(message)
            with self._lock:
                self._map_state, self._map_message = MapState.FAILED, message
            return None
        message = (
            f'Map {self.path} ready: {len(pmap)} points at {pmap.voxel_size:g} m, '
            f'{"oriented by its trajectory" if pmap.oriented else "no trajectory beside it"}, '
            f'in {time.monotonic() - t0:.1f} s.'
        )
        self._log.info(message)
        with self._lock:
            self._map_state, self._map_message = MapState.READY, message
        return pmap

    def _place(self, localizer: Localizer, item: LocalizationInput) -> None:
        """Place ``item``'s scan, publish what it gave and say what changed."""
        before = None if localizer.T_map_odom is None else localizer.T_map_odom.copy()
        t0 = time.perf_counter()
        track = localizer.update(item.scan, item.T_world_lidar)
        ms = (time.perf_counter() - t0) * 1e3
        best = track.result.best
        with self._lock:
            self._counts['updates'] += 1
            if track.searched:
                self._counts['searched'] += 1
            elif track.T_map_scan is not None:
                self._counts['tracked'] += 1
            else:
                self._counts['misses'] += 1  # tracking missed; enough in a row: lost
            if track.T_map_odom is not None:
                self._T_map_world = (item.generation, track.T_map_odom.copy())
            self._last_message, self._last_ms = track.message, ms
            self._last_fit = best.fit if best is not None else float('nan')
        if track.searched and track.T_map_scan is not None:
            self._note_state(track.state, *self._placement(track, item, before), placed=True)
        else:
            self._note_state(track.state, track.message)
        if track.T_map_scan is not None:
            self._publish_pose(track, item)

    def _placement(
        self, track: TrackStep, item: LocalizationInput, before: FloatArray | None
    ) -> tuple[str, bool]:
        """What a search's placement says (where, and the correction of the map frame it
        makes), and whether that correction is a jump past the tracking gates."""
        assert track.T_map_scan is not None
        loc = self._config.localization
        best = track.result.best
        fit = f', fit {best.fit:.2f}' if best is not None else ''
        T_map_moving = track.T_map_scan @ invert_transform(item.T_moving_lidar)
        text = (
            f'{loc.agreement} consecutive scans agree{fit}; the moving frame is at '
            f'{np.round(T_map_moving[:3, 3], 2).tolist()} m in {self._map_frame}'
        )
        if before is None:
            return f'{text}; publishing {self._map_frame} -> odom.', False
        D = invert_transform(before @ item.T_world_lidar) @ track.T_map_scan
        distance, angle = np.linalg.norm(D[:3, 3]), np.degrees(rotation_angle(D[:3, :3]))
        with self._lock:
            self._counts['relocalizations'] += 1
        text += f'; {self._map_frame} -> odom corrected by {distance:.2f} m and {angle:.1f} deg.'
        return text, bool(distance > loc.tracking_distance or angle > loc.tracking_angle_deg)

    def _note_state(
        self, state: TrackingState, why: str, jump: bool = False, *, placed: bool = False
    ) -> None:
        """Publish and log a change of state, and log a search's placement even without one
        (a warning when lost, ambiguous, or placed by a correction past the tracking gates)."""
        with self._lock:
            old, self._state = self._state, state
        if state != old:
            self.state_pub.publish(String(data=str(state)))
        elif not placed:
            return
        text = f'Localization {old} -> {state}: {why}'
        if jump or state in (TrackingState.LOST, TrackingState.AMBIGUOUS):
            self._log.warning(text)
        else:
            self._log.info(text)

    def _publish_pose(self, track: TrackStep, item: LocalizationInput) -> None:
        """``~/pose``: the moving frame's pose in the map at the scan's stamp, with the
        localization's covariance carried to the moving frame."""
        assert track.T_map_scan is not None
        T_ml = item.T_moving_lidar
        T_map_moving = track.T_map_scan @ invert_transform(T_ml)
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = stamp_to_msg(item.stamp_ns)
        msg.header.frame_id = self._map_frame
        msg.pose.pose = pose_to_msg(T_map_moving)
        cov = track.result.covariance
        if cov is not None:
            cov_map_lidar = pose_covariance_in_map(np.asarray(cov), track.T_map_scan)
            moved = pose_covariance_in_base(cov_map_lidar, T_ml, T_map_moving, np.eye(4))
            msg.pose.covariance = covariance_to_msg(moved)
        self.pose_pub.publish(msg)

    def _on_error(self, exc: Exception, item: LocalizationInput) -> None:
        """Count an unexpected error, skip the scan; the traceback once per kind."""
        with self._lock:
            self._counts['errors'] += 1
        self._errors.log(
            exc,
            f'Unexpected error localizing the scan stamped {item.stamp_ns * 1e-9:.3f} s '
            f'({type(exc).__name__}: {exc}): skipped, the localization goes on.',
        )
