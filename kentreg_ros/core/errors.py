"""Exception hierarchy of kentreg_ros.

Every error raised on purpose by the library derives from :class:`KentRegError`, so callers
can catch one type. Messages name the offending value and what was expected. Errors of one
layer that need a name of their own extend this tree in that layer
(:mod:`kentreg_ros.io.errors`: scan, pose, bag and parameter errors; ``StartupError`` in
:mod:`kentreg_ros.ros.parameters`; ``CliError`` in :mod:`kentreg_ros.cli.common`). Anything
else that escapes the library (a ``RuntimeError``, an ``IndexError``) is a bug, not an input
the library refused.
"""


class KentRegError(Exception):
    """Base class of all kentreg errors."""


class ConfigError(KentRegError, ValueError):
    """A configuration value or key is invalid."""


class InvalidPointCloudError(KentRegError, ValueError):
    """A point cloud (array, message or file) is malformed or unusable."""


class DegenerateSceneError(KentRegError):
    """The scene does not constrain the transform (e.g. too few or coplanar points)."""


class InvalidInputError(KentRegError, ValueError, TypeError):
    """An argument other than a point cloud is malformed: a transform that is not rigid, a
    non-finite viewpoint, a configuration of the wrong type, a stamp that is not an integer.

    It is both a ``ValueError`` and a ``TypeError``, so code catching either keeps working.
    """
