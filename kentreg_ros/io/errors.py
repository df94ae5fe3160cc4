"""Errors raised by :mod:`kentreg_ros.io`.

They extend the hierarchy of :mod:`kentreg_ros.core.errors`, so ``except KentRegError`` catches
everything the library raises on purpose. Malformed point clouds (messages, arrays) raise
:class:`~kentreg_ros.core.errors.InvalidPointCloudError`; malformed scan files raise its subclass
:class:`ScanFileError`, which names the file. A refused parameter (the node's, a parameter file's
key, a command line's ``--set``) raises :class:`ParameterError`, a
:class:`~kentreg_ros.core.errors.ConfigError` naming the parameters.
"""

from __future__ import annotations

from kentreg_ros.core import ConfigError, InvalidPointCloudError, KentRegError


class ScanFileError(InvalidPointCloudError):
    """A scan file (PCD, PLY, KITTI ``.bin``, CSV) is missing, malformed or unsupported."""


class PoseFileError(KentRegError, ValueError):
    """A pose file (KITTI, TUM, ETH, BALM) is malformed or does not match the scans."""


class BagError(KentRegError):
    """A bag cannot be read or written: corrupt, truncated, wrong topic or message type."""


class ParameterError(ConfigError):
    """Named parameters (the node's, ``--set``, a parameter file's keys) are refused.

    ``str(exc)`` is the reason, as :class:`ConfigError` words it; ``names`` are the parameters
    it concerns (empty when it cannot tell which, e.g. a change of several at once that breaks
    a rule none breaks alone).

    Attributes
    ----------
    reason : str
        Why, naming the value and what was expected.
    names : tuple of str
        The refused parameters.
    """

    def __init__(self, reason: str, *, names: tuple[str, ...] = ()) -> None:
        super().__init__(reason)
        self.reason = reason
        self.names = tuple(names)

    def __reduce__(self) -> tuple[object, ...]:
        # Keyword-only state survives pickling (an error crossing a process boundary).
        return (_rebuild_parameter_error, (type(self), self.reason, self.names))


def _rebuild_parameter_error(
    cls: type[ParameterError], reason: str, names: tuple[str, ...]
) -> ParameterError:
    return cls(reason, names=names)


def describe_error(exc: BaseException) -> str:
    """The first line of an exception's message (its type's name when it has none)."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
