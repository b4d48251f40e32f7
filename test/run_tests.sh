#!/usr/bin/env bash
# Installs what is missing, checks the formatting (test/check_style.sh), builds everything and runs every test
# through CTest.
#
#   test/run_tests.sh [--preset default|asan|tsan] [--no-board] [extra ctest arguments, e.g. -R Lie -L integration]
#
# With the default preset and no extra ctest arguments it then cross-builds the agent for aarch64 and runs a
# fixed subset of its tests, and the real-data excerpt, under qemu (test/run_board_tests.sh); --no-board skips
# that. The deployment files' checks (label deploy) need the npm tools of deploy/install_deploy_tools.sh,
# which this script installs.
#
# Tests that need the real data ($CVISLAM_DATA_DIR, else ../shared/data) are reported as skipped, with
# the reason, when it is absent: never as passed.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
preset=default
board=1
while [ $# -gt 0 ]; do
  case "$1" in
    --preset) preset=$2; shift 2 ;;
    --no-board) board=0; shift ;;
    *) break ;;
  esac
done
if [ "$preset" != default ] || [ $# -gt 0 ]; then board=0; fi
case "$preset" in
  default|asan|tsan) ;;
  *) echo "run_tests: unknown preset '$preset' (use default, asan or tsan)" >&2; exit 2 ;;
esac

# A full run from a clean checkout writes about 4 GB (this build 2.6 GB, the aarch64 build, the sysroot and the
# simulator's renders). A full disk otherwise shows up minutes later as a linker error, so say it first and again
# if the build fails.
need_kb=$((5 * 1024 * 1024))
disk_note() {
  local free_kb
  free_kb=$(df -Pk "$repo" | awk 'NR == 2 { print $4 }')
  if [ "${free_kb:-0}" -lt "$need_kb" ]; then
    echo "run_tests: only $((free_kb / 1024)) MB free on the disk holding $repo; a full run needs about" \
      "$((need_kb / 1024)) MB. Free space there (old build/ folders, out/sim-cache) and run again." >&2
  fi
}
disk_note
"$repo/deploy/install_deps.sh"
"$repo/deploy/install_deploy_tools.sh"
cd "$repo"
rc=0
# Formatting first: a few seconds, and its failure is reported without stopping the tests.
test/check_style.sh || rc=1
build="build/$preset"
start=$(date +%s)
if [ ! -f "$build/build.ninja" ]; then
  cmake --preset "$preset" >/dev/null
fi
cmake --build --preset "$preset" || { disk_note; exit 1; }
echo "run_tests: build took $(( $(date +%s) - start )) s"
junit="$build/ctest-junit.xml"
ctest --preset "$preset" --output-junit "$PWD/$junit" "$@" || rc=$?
. "$repo/test/ctest_summary.sh"
ctest_summary "$junit" ctest
if [ "$board" -eq 1 ]; then
  "$repo/test/run_board_tests.sh" || rc=1
fi
exit "$rc"
