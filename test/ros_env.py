"""DDS settings for tests that start ROS nodes: loopback only, a test-only domain per session.

Every process that starts a ROS node in the tests must run with these variables: the test
process itself (``conftest.py`` applies them in ``pytest_configure``, before any
``rclpy.init``) and every subprocess it starts (they inherit ``os.environ``; pass
``env={**os.environ, **ros_env()}`` when building an environment by hand).

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and ``FASTRTPS_DEFAULT_PROFILES_FILE`` (the
  profile in ``test/fastdds_localhost.xml``: shared memory plus UDP whitelisted to 127.0.0.1,
  the built-in transports off, as ``config/fastdds_shm.xml`` ships it): no DDS traffic leaves
  this machine, and MB-sized clouds go through shared memory.
- ``ROS_DOMAIN_ID``: one value per test session in ``[DOMAIN_ID_MIN, DOMAIN_ID_MAX]``, derived
  from the process id, so test runs of several people or CI jobs on one machine rarely share
  a domain (tests also use unique topic names, and unique node names where they ask the
  graph about a node, so a shared domain does not break them). Fast
  DDS maps domain ``d`` to UDP ports from ``7400 + 250 d``; ids up to 101 keep those ports
  below the Linux ephemeral range (32768+). ``KENTREG_TEST_ROS_DOMAIN_ID`` fixes the value.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

#: Test-only domain ids (ROS 2 users mostly run 0 and small ids; 101 is the Linux maximum).
DOMAIN_ID_MIN = 60
DOMAIN_ID_MAX = 99
PROFILE = Path(__file__).resolve().parent / 'fastdds_localhost.xml'
_SESSION_DOMAIN_ID = DOMAIN_ID_MIN + os.getpid() % (DOMAIN_ID_MAX - DOMAIN_ID_MIN + 1)


def domain_id() -> int:
    """This session's test-only ``ROS_DOMAIN_ID`` (``KENTREG_TEST_ROS_DOMAIN_ID`` overrides)."""
    fixed = os.environ.get('KENTREG_TEST_ROS_DOMAIN_ID', '').strip()
    if fixed:
        value = int(fixed)
        if not 0 <= value <= 101:
            raise ValueError(f'Expected KENTREG_TEST_ROS_DOMAIN_ID in [0, 101], got {value}.')
        return value
    return _SESSION_DOMAIN_ID


def ros_env() -> dict[str, str]:
    """Environment variables that keep DDS on loopback in a test-only domain."""
    return {
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
        'FASTRTPS_DEFAULT_PROFILES_FILE': str(PROFILE),
        'ROS_DOMAIN_ID': str(domain_id()),
    }


def apply_ros_env() -> dict[str, str]:
    """Put :func:`ros_env` into ``os.environ`` (before the first ``rclpy.init``); return it."""
    env = ros_env()
    os.environ.update(env)
    return env


def unique_topic(name: str) -> str:
    """An absolute topic name no other test (or test run) uses: ``/kentreg_test_<hex>/name``."""
    return f'/kentreg_test_{uuid.uuid4().hex[:12]}/{name.lstrip("/")}'
