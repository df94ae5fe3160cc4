#!/usr/bin/env bash
# Build and test kentreg_ros as an ament_python package with colcon from PyPI, in a throw-away
# workspace, the way `colcon build && colcon test` runs on a ROS 2 Jazzy machine.
#
#   bash test/colcon_check.sh            # the ROS-facing subset (see COLCON_PYTEST_ARGS below)
#   bash test/colcon_check.sh --all      # the whole pytest suite under colcon test
#
# Fails (non-zero) when the build fails, when the install tree lacks the ament resource marker,
# package.xml, the config or launch file or the kentreg_node executable under lib/kentreg_ros
# (what `ros2 run kentreg_ros kentreg_node` executes), when a test fails, and when colcon test
# ran no test at all: pytest's "no tests collected" is not an error for colcon, and
# `colcon test` alone exits 0 on failures, hence --return-code-on-test-failure, `colcon
# test-result` and the count read from the JUnit file below.
#
# colcon-core requires setuptools < 80 (newer setuptools removed what its ament_python/python
# build and test steps rely on; with them a package whose pytest dependency is declared through
# tests_require silently ran 0 tests). kentreg_ros declares pytest in extras_require['test'],
# which colcon also reads, so its test step does not depend on tests_require.
set -euo pipefail
cd "$(dirname "$0")/.."
REPO="$PWD"
PKG=kentreg_ros

ALL=0
if [[ "${1:-}" == "--all" ]]; then ALL=1; fi

python3 -m pip install --quiet --disable-pip-version-check \
  'setuptools<80' colcon-core colcon-ros colcon-test-result colcon-package-selection

export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export FASTRTPS_DEFAULT_PROFILES_FILE="$REPO/test/fastdds_localhost.xml"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((60 + $$ % 40))}"

WS="$(mktemp -d "${TMPDIR:-/tmp}/kentreg_colcon.XXXXXX")"
cleanup() { rm -rf "$WS"; }
trap cleanup EXIT
mkdir "$WS/src"
# A symlink: colcon builds out of tree (build/, install/, log/ stay in $WS), and the working
# tree under test is exactly the one being checked.
ln -s "$REPO" "$WS/src/$PKG"
cd "$WS"

fail() {
  echo "colcon_check: FAILED: $*" >&2
  exit 1
}

show_log() {
  # colcon keeps each step's full output in log/latest_<verb>/<package>/stdout_stderr.log.
  local verb=$1
  find "log/latest_$verb/" -name 'stdout_stderr.log' -exec tail -n 60 {} + >&2 || true
}

echo "colcon_check: colcon build --packages-select $PKG (workspace $WS)"
if ! colcon build --packages-select "$PKG" --event-handlers console_direct- >/dev/null; then
  show_log build
  fail 'colcon build'
fi

INSTALL="$WS/install/$PKG"
for path in \
  "share/ament_index/resource_index/packages/$PKG" \
  "share/$PKG/package.xml" \
  "share/$PKG/config/kentreg.yaml" \
  "share/$PKG/launch/kentreg.launch.py" \
  "share/$PKG/rviz/kentreg.rviz"; do
  [[ -f "$INSTALL/$path" ]] || fail "install tree lacks $path"
done
for exe in kentreg_node kentreg_play kentreg_replay; do
  [[ -x "$INSTALL/lib/$PKG/$exe" ]] || fail "install tree lacks the executable lib/$PKG/$exe"
done
# Run the installed executables as `ros2 run kentreg_ros <exe>` does (lib/kentreg_ros/<exe>, with
# the environment colcon generated), on input that makes them stop at once: the node on an
# invalid startup parameter (it exits non-zero naming it), the player on a missing bag (exit 2).
# Both must import kentreg_ros from the install tree, not from the source checkout.
run_installed() {
  (
    set +u
    # shellcheck disable=SC1091
    source "$WS/install/local_setup.sh"
    set -u
    cd /
    "$@"
  )
}
out="$(run_installed "$INSTALL/lib/$PKG/kentreg_node" --ros-args -p qos_reliability:=bogus 2>&1)" &&
  fail "installed kentreg_node accepted an invalid parameter: $out"
[[ "$out" == *qos_reliability* && "$out" != *Traceback* ]] ||
  fail "installed kentreg_node did not report the invalid parameter: $out"
status=0
out="$(run_installed "$INSTALL/lib/$PKG/kentreg_play" "$WS/no_such_bag" 2>&1)" || status=$?
[[ "$status" == 2 && "$out" == *"no such file or folder"* ]] ||
  fail "installed kentreg_play: expected exit 2 on a missing bag, got $status: $out"
run_installed python3 -c "import kentreg_ros; print(kentreg_ros.__file__)" | grep -q "^$INSTALL/" ||
  fail "kentreg_ros is not imported from $INSTALL after sourcing install/local_setup.sh"
echo "colcon_check: install tree complete (marker, package.xml, config, launch, rviz, lib/$PKG/kentreg_node)"

# What colcon test runs: by default the tests of the ROS-facing packaging (launch file and the
# install tree seen through the ament index, which only runs here; kentreg_play over real rclpy;
# the node in-process, its frames, drop-in outputs, RViz file, parameters and message
# conversions; the generated parameter table). With a sourced tf2_ros the frame tests still
# use their stand-ins; the launch file loads for real.
# The whole suite already ran in test/run_tests.sh; --all repeats it under colcon.
if [[ "$ALL" == 1 ]]; then
  PYTEST_ARGS=()
else
  PYTEST_ARGS=(test/ros/test_launch.py test/ros/test_play.py test/test_docs.py
    test/ros/test_ros_node.py test/ros/test_ros_dropin.py test/ros/test_ros_frames.py
    test/io/test_parameters.py test/ros/test_ros_messages.py)
fi
if [[ -n "${COLCON_PYTEST_ARGS:-}" ]]; then
  read -r -a PYTEST_ARGS <<< "$COLCON_PYTEST_ARGS"
fi

echo "colcon_check: colcon test --packages-select $PKG ${PYTEST_ARGS[*]:-(whole suite)}"
test_status=0
colcon test --packages-select "$PKG" --return-code-on-test-failure \
  --event-handlers console_direct- \
  ${PYTEST_ARGS[@]+--pytest-args "${PYTEST_ARGS[@]}"} >/dev/null || test_status=$?
if ! colcon test-result --test-result-base "build/$PKG" --verbose; then
  show_log test
  fail 'colcon test-result reports failed tests'
fi
if [[ "$test_status" != 0 ]]; then
  show_log test
  fail "colcon test exited $test_status"
fi

JUNIT="$WS/build/$PKG/pytest.xml"
[[ -f "$JUNIT" ]] || fail "colcon test wrote no $JUNIT"
python3 - "$JUNIT" <<'EOF' || fail 'colcon test ran no test, or skipped the install-tree test'
import sys
import xml.etree.ElementTree as ET

root = ET.parse(sys.argv[1]).getroot()
suites = [root] if root.tag == 'testsuite' else list(root.iter('testsuite'))
tests = sum(int(s.get('tests', 0)) for s in suites)
skipped = sum(int(s.get('skipped', 0)) for s in suites)
bad = sum(int(s.get('failures', 0)) + int(s.get('errors', 0)) for s in suites)
cases = {c.get('name'): c for c in root.iter('testcase')}
print(
    f'colcon_check: JUnit: {tests} tests, {tests - skipped - bad} passed, {skipped} skipped, '
    f'{bad} failed'
)
if tests - skipped == 0 or bad:
    sys.exit(1)
# This test sees the package through the ament index, which only works with the install tree
# on AMENT_PREFIX_PATH: when collected, it must have run (proof colcon tested the install).
wanted = 'test_installed_package_has_marker_manifest_config_launch_and_executable'
if wanted in cases and cases[wanted].find('skipped') is not None:
    print(f'colcon_check: {wanted} was skipped under colcon test', file=sys.stderr)
    sys.exit(1)
EOF
echo 'colcon_check: OK'
