#!/usr/bin/env bash
# The README's test command: install everything the tests need, lint, type-check, build and test
# the ROS 2 package with colcon (test/colcon_check.sh), then the whole pytest suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet --disable-pip-version-check -e '.[test,ros,cluster]'
# DDS stays on loopback, in a test-only domain (60..99; test/conftest.py picks one per pytest
# session the same way, KENTREG_TEST_ROS_DOMAIN_ID fixes it).
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export FASTRTPS_DEFAULT_PROFILES_FILE="$PWD/test/fastdds_localhost.xml"
export ROS_DOMAIN_ID="${KENTREG_TEST_ROS_DOMAIN_ID:-$((60 + $$ % 40))}"
python3 -m ruff check .
python3 -m ruff format --check .
python3 -m mypy
bash test/colcon_check.sh
python3 -m pytest -q "$@"
