#!/usr/bin/env bash
# The main job with --trace and --metrics on a short mission (two agents and the server as separate processes over
# loopback):
#  - its traces parse, every span closes on a named thread, the ids join up across the processes, and
#    cvislam_trace aligns the clocks and recovers an offset injected into one agent's trace (check_mission_trace.py);
#  - /metrics, scraped every second while the mission runs, parses with Prometheus' own parser, its counters never
#    go back, and after the agents end they match the server's stats.json (check_mission_metrics.py).
#
#   mission_observability_test.sh REPO BUILD_DIR
set -euo pipefail
repo=$1
build=$2
tmp=$(mktemp -d)
scraper=""
cleanup() {
  [ -z "$scraper" ] || kill "$scraper" 2>/dev/null || true
  rm -rf "$tmp"
}
trap cleanup EXIT
if pgrep -x iox-roudi >/dev/null; then
  echo "mission_observability_test: an iox-roudi runs already; this test needs the machine's only one" >&2
  exit 1
fi
# The agents hand each keyframe to the link after its local BA, in one delta (not the default), so that this path
# too is run end to end: its keyframes must join up in the traces and its counters match like the default path's.
printf 'link:\n  keyframe_before_local_ba: false\n' >"$tmp/agent.yaml"
CVISLAM_SIM_CACHE="$tmp/cache" timeout 600 "$repo/deploy/run_mission.sh" --build-dir "$build" --duration 12 \
  --no-real --trace --metrics --agent-config "$tmp/agent.yaml" --out "$tmp/out" >"$tmp/log" 2>&1 &
mission=$!
# Scrapes /metrics every second from the moment the server says where it serves them until the mission ends.
mkdir -p "$tmp/scrapes"
(
  port=""
  while [ -z "$port" ] && kill -0 "$mission" 2>/dev/null; do
    port=$(sed -n 's/^metrics on port \([0-9]*\).*/\1/p' "$tmp/out/server.log" 2>/dev/null | head -1) || true
    sleep 0.2
  done
  n=0
  while kill -0 "$mission" 2>/dev/null; do
    n=$((n + 1))
    curl -sf "http://127.0.0.1:$port/metrics" -o "$tmp/scrapes/$(printf '%04d' "$n").txt" || rm -f "$tmp/scrapes/$(printf '%04d' "$n").txt"
    sleep 1
  done
) &
scraper=$!
if ! wait "$mission"; then
  echo "mission_observability_test: the mission failed; its output ends:" >&2
  tail -30 "$tmp/log" >&2
  exit 1
fi
wait "$scraper" || true
scraper=""
grep -q "joined trace: $tmp/out/trace/mission_trace.json" "$tmp/log" ||
  { echo "mission_observability_test: the main job printed no joined trace" >&2; tail -30 "$tmp/log" >&2; exit 1; }
python3 "$repo/test/deploy/check_mission_trace.py" "$tmp/out/trace" "$build/bin/cvislam_trace"
# Debian's python3: python3-prometheus-client installs there (install_deps.sh).
/usr/bin/python3 "$repo/test/deploy/check_mission_metrics.py" "$tmp/scrapes" "$tmp/out/server/metrics.txt" \
  "$tmp/out/server/stats.json" overlap2
