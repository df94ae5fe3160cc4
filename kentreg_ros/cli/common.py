"""What every kentreg command line shares: option types, ``--config``/``--set``, one way to fail.

A command line builds its parser with :class:`ArgumentParser`, whose usage errors raise
:class:`CliError` instead of printing the usage and exiting, and runs its work through
:func:`run_main`: bad input of any kind (:class:`CliError`, any
:class:`~kentreg_ros.core.errors.KentRegError`, ``ValueError``, ``OSError``) becomes one line
``<prog>: error: <message>`` on stderr and exit status 2, Ctrl-C exit status 130.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

from kentreg_ros.core import KentRegConfig, KentRegError
from kentreg_ros.io.paramfile import effective_config

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class CliError(KentRegError):
    """Bad command-line input: shown as ``<prog>: error: <message>``, exit status 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose usage errors raise :class:`CliError` (one line, exit 2 via
    :func:`run_main`) instead of printing the usage; ``--help`` and ``--version`` still exit 0.
    """

    def error(self, message: str) -> NoReturn:
        raise CliError(message)


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message, or its type name when it has none."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def interrupt_through_rclpy() -> None:
    """Let Ctrl-C reach a ROS program only through rclpy (call before ``rclpy.init``).

    SIGINT is ignored at Python's level; ``rclpy.init`` then installs its own handler on top,
    which on Ctrl-C shuts the context down, so the program ends through
    ``ExternalShutdownException`` at a point of its choosing and Python never raises
    ``KeyboardInterrupt`` at an arbitrary one (inside an rclpy call, during the cleanup). When
    rclpy uninstalls its handler at shutdown, the ignored disposition comes back and survives
    the interpreter's finalization, so a Ctrl-C pressed again while the program exits cannot
    kill it by the signal either. ``kentreg_play`` exited -2 instead of 130 a few times in
    about 15 colcon runs, after its clean shutdown had printed its summary; a KeyboardInterrupt
    that CPython 3.11 still counts as unhandled at exit is the likely cause (not proven: it
    did not reproduce on demand). Main thread only; elsewhere a no-op.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_main(prog: str, body: Callable[[], int], *, interrupted: str = 'interrupted') -> int:
    """Run a command line's work and turn its failures into an exit status.

    Returns what ``body`` returns; on :class:`CliError`, ``KentRegError``, ``ValueError`` or
    ``OSError`` prints ``<prog>: error: <first line of the message>`` to stderr and returns
    :data:`EXIT_BAD_INPUT` (2); on Ctrl-C prints ``<prog>: <interrupted>`` and returns
    :data:`EXIT_INTERRUPTED` (130). Any other exception is a bug and propagates.
    """
    try:
        return body()
    except KeyboardInterrupt:
        print(f'{prog}: {interrupted}', file=sys.stderr)
        return EXIT_INTERRUPTED
    except (KentRegError, ValueError, OSError) as exc:
        print(f'{prog}: error: {one_line(exc)}', file=sys.stderr)
        return EXIT_BAD_INPUT


# --------------------------------------------------------------------------------------------
# Option value types: argparse reports their ArgumentTypeError as
# "argument --name: <message>".


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected an integer, got {text!r}') from None


def non_negative_int(text: str) -> int:
    """An integer >= 0, or an ``ArgumentTypeError`` naming the text."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f'expected a non-negative integer (>= 0), got {text!r}')
    return value


def positive_int(text: str) -> int:
    """An integer >= 1, or an ``ArgumentTypeError`` naming the text (also for negatives)."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'expected a positive integer (>= 1), got {text!r}')
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0, or an ``ArgumentTypeError`` naming the text."""
    value = _finite_float(text)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f'expected a finite number >= 0, got {text!r}')
    return value


def positive_float(text: str) -> float:
    """A finite number > 0, or an ``ArgumentTypeError`` naming the text."""
    value = _finite_float(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f'expected a finite number > 0, got {text!r}')
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected a number, got {text!r}') from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'expected a finite number, got {text!r}')
    return value


def key_value(text: str) -> str:
    """A ``KEY=VALUE`` item with a non-empty key, returned as given."""
    key, sep, _ = text.partition('=')
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f'expected KEY=VALUE, got {text!r}')
    return text


# --------------------------------------------------------------------------------------------
# Configuration: --config FILE and --set KEY=VALUE


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--config FILE`` and ``--set KEY=VALUE`` (repeatable, into ``args.overrides``)."""
    parser.add_argument(
        '--config',
        type=Path,
        help="parameter file (the node's YAML, e.g. config/kentreg.yaml); default: the "
        'built-in defaults, which that file repeats',
    )
    parser.add_argument(
        '--set',
        dest='overrides',
        action='append',
        default=[],
        type=key_value,
        metavar='KEY=VALUE',
        help='override one parameter, e.g. --set mode=paper --set odometry.constant_velocity='
        'false (repeatable)',
    )


def config_from_args(args: argparse.Namespace) -> KentRegConfig:
    """The configuration given by ``--config`` and ``--set`` (see :func:`add_config_options`).

    Raises
    ------
    ConfigError
        Unreadable file, unknown key or invalid value.
    """
    return effective_config(args.config, args.overrides)


# --------------------------------------------------------------------------------------------
# Output: log lines and the progress bar on stderr


class _Formatter(logging.Formatter):
    """``<prog>: <LEVEL>: <message>``; INFO records without the level unless ``info_level``."""

    def __init__(self, prog: str, *, info_level: bool) -> None:
        super().__init__(f'{prog}: %(levelname)s: %(message)s')
        self._plain = logging.Formatter(f'{prog}: %(message)s')
        self._info_level = info_level

    def format(self, record: logging.LogRecord) -> str:
        if record.levelno == logging.INFO and not self._info_level:
            return self._plain.format(record)
        return super().format(record)


@contextlib.contextmanager
def logging_to_stderr(prog: str, level: int, *, info_level: bool = True) -> Iterator[None]:
    """Show the package's log records at ``level`` and above on stderr while the block runs.

    Lines read ``<prog>: <LEVEL>: <message>``; with ``info_level=False`` INFO records (a
    command's own progress report) read ``<prog>: <message>``. The handler is removed
    afterwards, so a command line run twice in one process (tests) does not print twice.
    """
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter(prog, info_level=info_level))
    package = logging.getLogger('kentreg_ros')
    previous = package.level
    package.addHandler(handler)
    package.setLevel(level)
    try:
        yield
    finally:
        package.removeHandler(handler)
        package.setLevel(previous)


@contextlib.contextmanager
def progress_bar(
    prog: str,
    total: int | None,
    *,
    enabled: bool = True,
    terminal_only: bool = False,
    unit: str = 'scan',
) -> Iterator[Any]:
    """A tqdm bar on stderr counting ``unit`` (log records printed above it), or None when
    disabled or when tqdm is not installed (then said once at INFO). ``terminal_only`` hides it
    when stderr is not a terminal."""
    if not enabled:
        yield None
        return
    try:
        from tqdm import tqdm
        from tqdm.contrib.logging import logging_redirect_tqdm
    except ImportError:
        logging.getLogger(__name__).info(
            'tqdm is not installed: no progress bar (pip install tqdm).'
        )
        yield None
        return
    bar = tqdm(
        total=total,
        unit=unit,
        desc=prog,
        file=sys.stderr,
        dynamic_ncols=True,
        mininterval=0.5,
        leave=True,
        disable=None if terminal_only else False,
    )
    try:
        with logging_redirect_tqdm(loggers=[logging.getLogger('kentreg_ros')]):
            yield bar
    finally:
        bar.close()
