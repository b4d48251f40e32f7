#!/usr/bin/env bash
# The main job with --trace on a short mission (two agents and the server as separate processes over loopback):
# its traces parse, every span closes on a named thread, the ids join up across the processes, and cvislam_trace
# aligns the clocks, and recovers an offset injected into one agent's trace (check_mission_trace.py).
#
#   mission_trace_test.sh REPO BUILD_DIR
set -euo pipefail
repo=$1
build=$2
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
if pgrep -x iox-roudi >/dev/null; then
  echo "mission_trace_test: an iox-roudi runs already; this test needs the machine's only one" >&2
  exit 1
fi
if ! CVISLAM_SIM_CACHE="$tmp/cache" timeout 600 "$repo/deploy/run_mission.sh" --build-dir "$build" --duration 12 \
  --no-real --trace --out "$tmp/out" >"$tmp/log" 2>&1; then
  echo "mission_trace_test: the mission failed; its output ends:" >&2
  tail -30 "$tmp/log" >&2
  exit 1
fi
grep -q "joined trace: $tmp/out/trace/mission_trace.json" "$tmp/log" ||
  { echo "mission_trace_test: the main job printed no joined trace" >&2; tail -30 "$tmp/log" >&2; exit 1; }
python3 "$repo/test/deploy/check_mission_trace.py" "$tmp/out/trace" "$build/bin/cvislam_trace"
