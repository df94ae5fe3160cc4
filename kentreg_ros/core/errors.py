"""Exception hierarchy of kentreg_ros.

Every error raised on purpose by the library derives from :class:`KentRegError`, so callers
can catch one type. Messages name the offending value and what was expected.
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
