# Sourced by test/run_tests.sh and test/run_board_tests.sh.
# ctest_summary JUNIT LABEL: prints "LABEL: N passed, N failed, N skipped" from CTest's JUnit file. CTest folds
# skipped tests into "100% tests passed"; counting them apart keeps a run without the real data from passing for
# a full one.
ctest_summary() {
  local junit=$1 label=$2 total failed skipped
  [ -f "$junit" ] || return 0
  total=$(grep -c '<testcase ' "$junit" || true)
  failed=$(grep -c 'status="fail"' "$junit" || true)
  skipped=$(grep -Ec 'status="(notrun|disabled)"' "$junit" || true)
  echo "$label: $((total - failed - skipped)) passed, $failed failed, $skipped skipped"
}
