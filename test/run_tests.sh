#!/usr/bin/env bash
# The README's test command: install everything the tests need, lint, type-check, test.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install --quiet --disable-pip-version-check -e '.[test,ros]'
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export FASTRTPS_DEFAULT_PROFILES_FILE="$PWD/test/fastdds_localhost.xml"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-77}"
python3 -m ruff check .
python3 -m ruff format --check .
python3 -m mypy
python3 -m pytest -q "$@"
