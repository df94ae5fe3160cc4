"""The node's counters and its diagnostic_msgs/DiagnosticStatus: rates, latency, drops,
failures and the last step's health, per diagnostics window."""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from kentreg_ros.core import HEALTHS

#: Diagnostics turn WARN when no scan arrived for this many seconds.
STALE_INPUT_S = 5.0


class Counters:
    """Thread-safe event counters, cumulative and per diagnostics window."""

    NAMES = (
        'received',
        'processed',
        'published',
        'dropped_queue',
        'dropped_duplicate_stamp',
        'dropped_waiting_for_tf',
        'malformed',
        'nonfinite_points',
        'errors',
        'resets',
        'searched',
        *HEALTHS,
    )

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.total = dict.fromkeys(self.NAMES, 0)
        self.window = dict.fromkeys(self.NAMES, 0)

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.total[name] += n
            self.window[name] += n

    def take_window(self) -> tuple[dict[str, int], dict[str, int]]:
        """The totals and the window's counts; a new window starts."""
        with self._lock:
            window, self.window = self.window, dict.fromkeys(self.NAMES, 0)
            return dict(self.total), window


@dataclass(frozen=True)
class Snapshot:
    """What the worker last reported, read under the node's lock."""

    queued: int
    model: str
    pending_model: str
    latencies_ms: Sequence[float]
    steps_ms: Sequence[float]
    frame_id: str
    last_health: str
    last_message: str


def odometry_status(
    name: str,
    topic: str,
    total: Mapping[str, int],
    window: Mapping[str, int],
    period_s: float,
    since_input_s: float,
    snap: Snapshot,
) -> DiagnosticStatus:
    """The status of one diagnostics window: OK while tracking, WARN on fall-backs, rejections,
    drops, malformed input or stale input, ERROR after an unexpected error."""
    status = DiagnosticStatus()
    status.name = f'{name}: odometry'
    status.hardware_id = snap.frame_id
    level, message = DiagnosticStatus.OK, 'tracking'
    problems = []
    if window['fell_back'] or window['rejected']:
        problems.append(
            f'{window["fell_back"] + window["rejected"]} scans fell back or were rejected'
        )
    if window['errors']:
        problems.append(
            f'{window["errors"]} scans skipped after an unexpected error (see the log)'
        )
    if window['malformed']:
        problems.append(f'{window["malformed"]} malformed messages')
    if window['dropped_queue']:
        problems.append(f'{window["dropped_queue"]} scans dropped (worker busy)')
    if window['degenerate']:
        problems.append(f'{window["degenerate"]} degenerate scans')
    if problems:
        # An unexpected error is a fault of the node, not of its input: ERROR.
        level = DiagnosticStatus.ERROR if window['errors'] else DiagnosticStatus.WARN
        message = '; '.join(problems)
    if total['received'] == 0 or since_input_s > STALE_INPUT_S:
        level = max(level, DiagnosticStatus.WARN)
        message = f'no scans on {topic} for {since_input_s:.0f} s'
    status.level = level
    status.message = message
    lat, steps = snap.latencies_ms, snap.steps_ms
    values = {
        'input_rate_hz': f'{window["received"] / period_s:.2f}',
        'output_rate_hz': f'{window["published"] / period_s:.2f}',
        'latency_ms_mean': f'{np.mean(lat):.1f}' if len(lat) else 'nan',
        'latency_ms_max': f'{np.max(lat):.1f}' if len(lat) else 'nan',
        'step_ms_mean': f'{np.mean(steps):.1f}' if len(steps) else 'nan',
        'queue_length': str(snap.queued),
        'last_health': snap.last_health,
        'last_message': snap.last_message,
        'model': snap.model,  # in use; an accepted change applies from the next scan
        'pending_model': snap.pending_model,
    }
    values.update({f'total.{k}': str(v) for k, v in total.items()})
    values.update({f'window.{k}': str(v) for k, v in window.items()})
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status


@dataclass(frozen=True)
class LocalizationSnapshot:
    """What the localization thread last reported (:class:`~kentreg_ros.ros.localization.
    LocalizationWorker`), read under its lock."""

    map_file: str
    #: 'loading', 'ready' or 'failed'.
    map_state: str
    map_message: str
    state: str
    last_message: str
    last_fit: float
    last_ms: float
    counts: Mapping[str, int]


def localization_status(name: str, snap: LocalizationSnapshot) -> DiagnosticStatus:
    """The localization's status: OK while localized, WARN while the map loads or the node
    searches, is lost or ambiguous, ERROR when the map could not be loaded."""
    status = DiagnosticStatus()
    status.name = f'{name}: localization'
    status.hardware_id = snap.map_file
    if snap.map_state == 'failed':
        status.level, status.message = DiagnosticStatus.ERROR, snap.map_message
    elif snap.map_state == 'loading':
        status.level, status.message = DiagnosticStatus.WARN, snap.map_message
    elif snap.state == 'localized':
        status.level, status.message = DiagnosticStatus.OK, 'localized'
    else:
        status.level = DiagnosticStatus.WARN
        status.message = f'{snap.state}: {snap.last_message}' if snap.last_message else snap.state
    values = {
        'state': snap.state,
        'map_file': snap.map_file,
        'map': snap.map_state,
        'map_message': snap.map_message,
        'last_message': snap.last_message,
        'last_fit': f'{snap.last_fit:.3f}',
        'last_ms': f'{snap.last_ms:.1f}',
    }
    values.update({k: str(v) for k, v in snap.counts.items()})
    status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
    return status
