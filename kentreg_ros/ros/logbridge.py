"""The package's Python log records on a node's rclpy logger, so they reach ``/rosout``.

The core, ``io`` and ``eval`` log through ``logging.getLogger(__name__)`` (library code never
prints). In a ROS process nothing shows those records but Python's last-resort handler, which
prints WARNING and above to stderr and nothing of it reaches ``/rosout``, rqt_console or a
launch log. :class:`RclpyLogHandler` forwards every record of the ``kentreg_ros`` logger to a
node's rclpy logger at the matching severity, throttled per kind of message: a rejected scan
leaves a WARN on ``/rosout``, a sensor that sends nothing but rejected scans one WARN every
throttle period with the count of those held back.

The node attaches it when it starts and removes it when it is destroyed
(:meth:`RclpyLogHandler.attach`, :meth:`RclpyLogHandler.detach`); nothing is attached at import.
While at least one handler is attached and nobody chose a level for the ``kentreg_ros`` logger,
that logger takes the rclpy logger's level (``--ros-args --log-level kentreg_node:=debug``
shows the core's debug records too); the level is restored when the last handler goes.

Several nodes in one process: a record logged on a thread a handler owns (the node's worker,
see :meth:`RclpyLogHandler.own_thread`) goes to that node's logger only; records of other
threads go to every node's.

What the node's own threads log of an unexpected error (a bug they survive) is
:class:`UnexpectedErrors`: the traceback once per kind of error, then one throttled line.
"""

from __future__ import annotations

import collections
import logging
import re
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any, ClassVar

__all__ = ['PACKAGE_LOGGER', 'RclpyLogHandler', 'UnexpectedErrors']

#: The logger every module of the package logs under.
PACKAGE_LOGGER = 'kentreg_ros'
#: Kinds of message whose last time is remembered for throttling (oldest forgotten first): far
#: more than the package has kinds of message, so a forgotten kind is one that stopped coming.
MAX_KINDS = 256
#: Digits in a message: masked to tell its kind (scan indices, counts, stamps vary).
_NUMBER = re.compile(r'\d+')
#: Kinds of unexpected error whose traceback is logged in full (each once); later kinds get the
#: one-line message only, so a node failing in ever new ways cannot fill its log.
MAX_ERROR_KINDS = 32


def _python_level(severity: int) -> int:
    """The Python logging level of an rcutils severity (the numbers coincide: DEBUG 10, INFO
    20, WARN 30, ERROR 40, FATAL 50); UNSET reads as INFO, rcutils' default."""
    return int(severity) or logging.INFO


class RclpyLogHandler(logging.Handler):
    """Forward Python log records to an rclpy logger, throttled per kind of message.

    The kind of a record is its logger, its level, its template (``record.msg``) and its text
    with every number masked: the template alone would let one kind of ``'Scan %d: %s'`` (a
    rejected scan) hide another (a scan that fell back). A kind seen less than ``throttle_s``
    ago is held back and counted; the next record of that kind that goes out says how many
    were held back. Tracebacks (``exc_info``) go out with the message.

    Parameters
    ----------
    logger : rclpy RcutilsLogger
        The node's logger (``node.get_logger()``).
    throttle_s : float
        Seconds between two records of the same kind, ``>= 0`` (0: none held back).
    clock : callable, optional
        Seconds of a monotonic clock (default :func:`time.monotonic`; tests pass their own).
    """

    _lock_attached: ClassVar[threading.Lock] = threading.Lock()
    _attached: ClassVar[list[RclpyLogHandler]] = []
    #: The package logger's own level before the first handler came (restored after the last).
    _saved_level: ClassVar[int | None] = None
    #: Thread ident -> the handler that owns the records logged on it.
    _owners: ClassVar[dict[int, RclpyLogHandler]] = {}

    def __init__(
        self, logger: Any, *, throttle_s: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if not throttle_s >= 0.0:
            raise ValueError(f'Expected `throttle_s` >= 0, got {throttle_s!r}.')
        super().__init__()
        self._logger = logger
        self._throttle_s = float(throttle_s)
        self._clock = clock
        self._last: collections.OrderedDict[tuple[Any, ...], float] = collections.OrderedDict()
        self._held: dict[tuple[Any, ...], int] = {}
        self.setFormatter(logging.Formatter('%(message)s'))

    # ----------------------------------------------------------------------------------------
    # Attaching

    def attach(self) -> RclpyLogHandler:
        """Add this handler to the package logger (and set its level, see the module)."""
        with self._lock_attached:
            package = logging.getLogger(PACKAGE_LOGGER)
            if not self._attached:
                type(self)._saved_level = package.level
            if self not in self._attached:
                self._attached.append(self)
                package.addHandler(self)
            self._apply_level(package)
        return self

    def detach(self) -> None:
        """Remove this handler (idempotent); the last one restores the package logger's level."""
        with self._lock_attached:
            package = logging.getLogger(PACKAGE_LOGGER)
            package.removeHandler(self)
            if self in self._attached:
                self._attached.remove(self)
            for ident in [i for i, h in self._owners.items() if h is self]:
                del self._owners[ident]
            if not self._attached:
                if self._saved_level is not None:
                    package.setLevel(self._saved_level)
                type(self)._saved_level = None
            else:
                self._apply_level(package)
        self.close()

    @classmethod
    def _apply_level(cls, package: logging.Logger) -> None:
        if cls._saved_level != logging.NOTSET:
            return  # someone chose the package's level: theirs stands
        levels = [_python_level(h._logger.get_effective_level()) for h in cls._attached]
        package.setLevel(min(levels))

    def own_thread(self, ident: int | None) -> None:
        """Records logged on thread ``ident`` go to this handler only (a node's worker)."""
        if ident is not None:
            with self._lock_attached:
                self._owners[ident] = self

    # ----------------------------------------------------------------------------------------
    # Forwarding

    def filter(self, record: logging.LogRecord) -> bool:
        """Drop records another handler's thread logged (see :meth:`own_thread`)."""
        owner = self._owners.get(record.thread) if record.thread is not None else None
        return (owner is None or owner is self) and bool(super().filter(record))

    def emit(self, record: logging.LogRecord) -> None:
        """Forward ``record`` unless its kind went out less than ``throttle_s`` ago."""
        try:
            message = self.format(record)
            kind = (
                record.name,
                record.levelno,
                str(record.msg),
                _NUMBER.sub('#', record.getMessage()),
            )
            now = self._clock()
            last = self._last.get(kind)
            if last is not None and now - last < self._throttle_s:
                self._held[kind] = self._held.get(kind, 0) + 1
                return
            held = self._held.pop(kind, 0)
            self._last[kind] = now
            self._last.move_to_end(kind)
            while len(self._last) > MAX_KINDS:
                forgotten, _ = self._last.popitem(last=False)
                self._held.pop(forgotten, None)
            if held and last is not None:
                message += f' ({held} more like this in the last {now - last:.0f} s not shown.)'
            self._log(record.levelno, message)
        except Exception:  # a logging handler never raises into the code that logged
            self.handleError(record)

    def _log(self, level: int, message: str) -> None:
        # One call site per severity: rclpy keys a logger's state by call site and refuses
        # a call site whose severity changes between calls.
        log = self._logger
        if level >= logging.CRITICAL:
            log.fatal(message)
        elif level >= logging.ERROR:
            log.error(message)
        elif level >= logging.WARNING:
            log.warning(message)
        elif level >= logging.INFO:
            log.info(message)
        else:
            log.debug(message)


class UnexpectedErrors:
    """What a node's thread logs of an unexpected error (a bug: the thread skips what it had in
    hand and goes on): its traceback once per kind of error (the exception's type and the line
    that raised it, for the first :data:`MAX_ERROR_KINDS` kinds), the one-line text otherwise,
    throttled. One instance per thread (the odometry's worker, the localization's).

    Parameters
    ----------
    log : rclpy logger
    throttle_s : float
        Seconds between repeated one-line texts.
    """

    def __init__(self, log: Any, throttle_s: float) -> None:
        self._log, self._throttle_s = log, throttle_s
        self._kinds: set[tuple[str, str, int]] = set()  # (type, file, line) logged in full

    def log(self, exc: BaseException, text: str) -> None:
        """Log ``text`` (what the error cost) as an error, with ``exc``'s traceback when its
        kind is new."""
        frames = traceback.extract_tb(exc.__traceback__)
        where = (frames[-1].filename, frames[-1].lineno or 0) if frames else ('', 0)
        kind = (type(exc).__qualname__, *where)
        if kind not in self._kinds and len(self._kinds) < MAX_ERROR_KINDS:
            self._kinds.add(kind)
            trace = ''.join(traceback.format_exception(exc)).rstrip()
            self._log.error(f'{text} Its traceback (shown once for this kind of error):\n{trace}')
        else:
            self._log.error(text, throttle_duration_sec=self._throttle_s)
