"""Errors raised by :mod:`kentreg_ros.io`.

They extend the hierarchy of :mod:`kentreg_ros.core.errors`, so ``except KentRegError`` catches
everything the library raises on purpose. Malformed point clouds (messages, arrays) raise
:class:`~kentreg_ros.core.errors.InvalidPointCloudError`; malformed scan files raise its subclass
:class:`ScanFileError`, which names the file.
"""

from kentreg_ros.core import InvalidPointCloudError, KentRegError


class ScanFileError(InvalidPointCloudError):
    """A scan file (PCD, PLY, KITTI ``.bin``, CSV) is missing, malformed or unsupported."""


class PoseFileError(KentRegError, ValueError):
    """A pose file (KITTI, TUM, ETH, BALM) is malformed or does not match the scans."""


class BagError(KentRegError):
    """A bag cannot be read or written: corrupt, truncated, wrong topic or message type."""


def describe_error(exc: BaseException) -> str:
    """The first line of an exception's message (its type's name when it has none)."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
