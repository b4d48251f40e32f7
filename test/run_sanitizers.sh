#!/usr/bin/env bash
# The sanitizer runs before a release (too long for CI's budget on two cores): ThreadSanitizer on the server and the
# agents in a two-agent mission and on every test that runs gRPC, threads or processes; AddressSanitizer with
# UndefinedBehaviorSanitizer on the whole suite, the integration tests included. Builds the tsan and asan presets
# (build/tsan, build/asan) as needed.
#
#   test/run_sanitizers.sh [--tsan-only | --asan-only] [--mission-seconds S]
#
# Reports go to build/sanitizers/ (one file per process: tsan.<pid>, asan.<pid>); the summary prints how many
# each run left, and the exit status is 1 when any report or failed test remains. test/sanitizers/tsan.supp holds
# the suppressions for what Debian's uninstrumented gRPC, protobuf and absl do, each with its reason.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$repo"
run_tsan=1
run_asan=1
mission_s=20
while [ $# -gt 0 ]; do
  case "$1" in
    --tsan-only) run_asan=0; shift ;;
    --asan-only) run_tsan=0; shift ;;
    --mission-seconds) mission_s=$2; shift 2 ;;
    -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
    *) echo "run_sanitizers: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
"$repo/deploy/install_deps.sh"
reports="$repo/build/sanitizers"
rm -rf "$reports"
mkdir -p "$reports"
status=0

count() { find "$reports" -name "$1.*" -type f | wc -l; }

if [ "$run_tsan" = 1 ]; then
  cmake --preset tsan >/dev/null  # again each time: a changed preset reaches an existing build folder
  cmake --build --preset tsan
  export TSAN_OPTIONS="suppressions=$repo/test/sanitizers/tsan.supp second_deadlock_stack=1 history_size=4 log_path=$reports/tsan exitcode=66"
  echo "== ThreadSanitizer: gRPC, link, store, scale-out and process tests"
  ctest --test-dir build/tsan -j2 --output-on-failure \
    -R "server_grpc|server_access_grpc|server_map_service|server_cluster|agent_link|LinkRoundTrip|LinkAllocations|MissionProcesses|scaleout|backend_concurrency|recognition_worker|agent_ipc|agent_test" \
    >"$reports/tsan-ctest.log" 2>&1 || { echo "  some tests failed under TSan (see $reports/tsan-ctest.log)"; status=1; }
  tail -3 "$reports/tsan-ctest.log"
  tests_reports=$(count tsan)
  echo "== ThreadSanitizer: a two-agent mission (overlap2, ${mission_s} s), server and agents instrumented"
  deploy/run_mission.sh --build-dir "$repo/build/tsan" --duration "$mission_s" --no-real --out "$reports/mission" \
    >"$reports/tsan-mission.log" 2>&1 || { echo "  the mission failed under TSan (see $reports/tsan-mission.log)"; status=1; }
  grep -E "^agent[01] |^joint" "$reports/tsan-mission.log" | head -3 || true
  mission_reports=$(( $(count tsan) - tests_reports ))
  echo "ThreadSanitizer reports: $tests_reports from the tests, $mission_reports from the mission (in $reports)"
  [ "$(count tsan)" -eq 0 ] || status=1
  unset TSAN_OPTIONS
fi

if [ "$run_asan" = 1 ]; then
  cmake --preset asan >/dev/null  # again each time: a changed preset reaches an existing build folder
  cmake --build --preset asan
  export ASAN_OPTIONS="detect_leaks=1 log_path=$reports/asan"
  export UBSAN_OPTIONS="print_stacktrace=1 halt_on_error=1 log_path=$reports/asan"
  echo "== AddressSanitizer and UndefinedBehaviorSanitizer: every test, the integration tests included"
  # The allocation-counting tests replace malloc and are not built with sanitizers. The deployment checks (label
  # deploy) are left out: they compare the default build's binaries with the container images' package lists, and
  # an instrumented binary links libasan and more by design.
  ctest --test-dir build/asan -j2 --output-on-failure --timeout 1800 -LE deploy >"$reports/asan-ctest.log" 2>&1 ||
    { echo "  some tests failed under ASan/UBSan (see $reports/asan-ctest.log)"; status=1; }
  tail -3 "$reports/asan-ctest.log"
  echo "AddressSanitizer/UBSan reports: $(count asan) (in $reports)"
  [ "$(count asan)" -eq 0 ] || status=1
fi
exit "$status"
