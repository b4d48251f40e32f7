#!/usr/bin/env bash
# What the live viewer costs the server: the main job run with 0, 1 and 10 viewers (the last of the 10 never reads),
# side by side. Per run: the server's CPU seconds and peak memory (VmHWM, read from /proc while it runs), every
# batch's ingest time (p50/p99 from stats.json, per agent), each reading viewer's bandwidth, and the size of the
# recording per minute of mission. A benchmark, not a test: it prints a table and writes JSON.
#
#   test/bench/viewer_load.sh [--preset overlap2] [--viewers "0 1 10"] [--duration 60] [--out DIR]
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
preset=overlap2
viewer_counts="0 1 10"
duration=60
out="$repo/out/bench/viewer_load"
while [ $# -gt 0 ]; do
  case "$1" in
    --preset) preset=$2; shift 2 ;;
    --viewers) viewer_counts=$2; shift 2 ;;
    --duration) duration=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    *) echo "viewer_load: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
tools=${CVISLAM_DEPLOY_TOOLS:-"$repo/out/deploy-tools"}
mkdir -p "$out"
results=()
for n in $viewer_counts; do
  run="$out/$preset-viewers$n"
  rm -rf "$run"
  "$repo/deploy/run_mission.sh" --preset "$preset" --duration "$duration" --no-real --viewer 127.0.0.1:0 \
    --out "$run" >"$out/$preset-viewers$n.log" 2>&1 &
  mission=$!
  port=""
  while [ -z "$port" ] && kill -0 "$mission" 2>/dev/null; do
    port=$(sed -n 's/^viewer on port \([0-9]*\).*/\1/p' "$run/server.log" 2>/dev/null | head -1) || true
    sleep 0.2
  done
  server=$(pgrep -n -x cvislam_server)
  token=$(awk -v m="$preset" '$1 == m { print $2 }' "$run/tokens")
  viewers=""
  if [ "$n" -gt 0 ]; then
    stalled=$(( n > 1 ? 1 : 0 ))
    node "$repo/test/viewer/viewers.mjs" --port "$port" --mission "$preset" --token "$token" --clients "$n" \
      --stalled "$stalled" --tools "$tools" >"$run.viewers.json" 2>&1 &
    viewers=$!
  fi
  cpu=0
  hwm=0
  tick=$(getconf CLK_TCK)
  while kill -0 "$server" 2>/dev/null; do
    if stat=$(cat "/proc/$server/stat" 2>/dev/null); then
      cpu=$(echo "$stat" | awk -v t="$tick" '{ printf "%.2f", ($14 + $15) / t }')
      hwm=$(awk '/VmHWM/ { print $2 }' "/proc/$server/status" 2>/dev/null || echo "$hwm")
    fi
    sleep 0.5
  done
  wait "$mission" || echo "viewer_load: the mission with $n viewers failed (see $out/$preset-viewers$n.log)" >&2
  [ -z "$viewers" ] || wait "$viewers" || true
  ingest=$(jq -c --arg m "$preset" '[.agents[] | select(.mission == $m) | {agent: .agent_id, p50: .ingest_ms.p50, p99: .ingest_ms.p99}]' "$run/server/stats.json")
  mcap_mb=$(du -b "$run/mission.mcap" | awk -v d="$duration" '{ printf "%.2f", $1 / 1e6 / (d / 60) }')
  bandwidth=$( [ -f "$run.viewers.json" ] && tail -1 "$run.viewers.json" || echo null)
  line="{\"viewers\": $n, \"server_cpu_s\": $cpu, \"server_peak_rss_mb\": $((hwm / 1024)), \"ingest_ms\": $ingest, \"mcap_mb_per_min\": $mcap_mb, \"viewer_traffic\": $bandwidth}"
  echo "$line"
  results+=("$line")
done
printf '[%s]\n' "$(IFS=,; echo "${results[*]}")" >"$out/$preset.json"
echo "viewer_load: $out/$preset.json"
