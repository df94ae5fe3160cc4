"""Optional libraries the tests use when they can: skip, saying why, when one cannot be used.

``pytest.importorskip`` skips only when a module is missing (``ModuleNotFoundError``); a
library that is installed but cannot load raises another ``ImportError`` and the test errors
(pytest 9.0 warns, 9.1 fails). Open3D is such a library: its wheels link the system's
libusb-1.0, so ``pip install open3d-cpu`` on a machine without it gives
``ImportError: libusb-1.0.so.0: cannot open shared object file`` on import.
"""

from __future__ import annotations

from types import ModuleType

import pytest

#: What to install when Open3D is installed but cannot load (the README says the same).
OPEN3D_SYSTEM_PACKAGE = 'libusb-1.0-0'


def import_open3d() -> ModuleType:
    """``open3d``, or skip the test: not installed, or installed but unable to load."""
    try:
        import open3d
    except ModuleNotFoundError as exc:
        pytest.skip(f"Open3D is not installed ({exc}; pip install -e '.[bench]')")
    except ImportError as exc:
        pytest.skip(
            f'Open3D is installed but cannot load ({exc}); its wheel needs the system libusb '
            f'(Debian/Ubuntu: apt-get install {OPEN3D_SYSTEM_PACKAGE})'
        )
    return open3d
