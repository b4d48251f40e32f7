#!/usr/bin/env bash
# The main job stops at once when its server will not start (here: a config file that does not exist): it exits
# non-zero, names the problem, and leaves no iceoryx RouDi behind to block the next run. Its clean-up once waited
# for every child process, RouDi included, which runs until told to stop.
#
#   run_mission_early_exit_test.sh REPO BUILD_DIR
set -euo pipefail
repo=$1
build=$2
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
fail() {
  echo "run_mission_early_exit_test: $*" >&2
  sed 's/^/  | /' "$tmp/log" >&2 || true
  # A hung run leaves its RouDi: stop it, so that the tests after this one can start theirs.
  pkill -TERM -x iox-roudi 2>/dev/null || true
  exit 1
}
if pgrep -x iox-roudi >/dev/null; then
  echo "run_mission_early_exit_test: an iox-roudi runs already; this test needs the machine's only one" >&2
  exit 1
fi

set +e
CVISLAM_SIM_CACHE="$tmp/cache" timeout 120 "$repo/deploy/run_mission.sh" --build-dir "$build" --duration 2 \
  --no-real --out "$tmp/out" --server-arg --config --server-arg "$tmp/missing.yaml" >"$tmp/log" 2>&1
rc=$?
set -e
[ "$rc" -ne 124 ] || fail "run_mission.sh still ran after 120 s"
[ "$rc" -ne 0 ] || fail "run_mission.sh succeeded with a server that cannot start"
grep -q "missing.yaml" "$tmp/log" || fail "the output does not name the missing config file"
if pgrep -x iox-roudi >/dev/null; then fail "an iox-roudi was left running"; fi
echo "run_mission_early_exit_test: exit $rc, the problem named, no RouDi left"
