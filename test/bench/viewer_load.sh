#!/usr/bin/env bash
# What the live viewer costs the server: the main job run with 0, 1 and 10 viewers (the last of the 10 never reads),
# side by side, each --repeat times. Per run: the CPU seconds of the server and of its two viewer threads (the
# feed, which also writes the recording, and the WebSocket endpoint), its peak memory (VmHWM), all read from /proc
# while it runs; every batch's ingest time (p50/p99 from stats.json, per agent); each reading viewer's bandwidth;
# the size of the recording per minute of flight. With 0 viewers the recording still runs (the main job always
# records). A benchmark, not a test: it prints one JSON line per run and writes them all to OUT/PRESET.json.
#
#   test/bench/viewer_load.sh [--preset overlap2] [--viewers "0 1 10"] [--repeat 1] [--duration 60] [--out DIR]
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
preset=overlap2
viewer_counts="0 1 10"
duration=60
repeat=1
out="$repo/out/bench/viewer_load"
while [ $# -gt 0 ]; do
  case "$1" in
    --preset) preset=$2; shift 2 ;;
    --viewers) viewer_counts=$2; shift 2 ;;
    --duration) duration=$2; shift 2 ;;
    --repeat) repeat=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    *) echo "viewer_load: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
tools=${CVISLAM_DEPLOY_TOOLS:-"$repo/out/deploy-tools"}
mkdir -p "$out"
results=()
for rep in $(seq "$repeat"); do
for n in $viewer_counts; do
  run="$out/$preset-viewers$n-run$rep"
  rm -rf "$run" "$run.viewers.json"
  "$repo/deploy/run_mission.sh" --preset "$preset" --duration "$duration" --no-real --viewer 127.0.0.1:0 \
    --out "$run" >"$run.log" 2>&1 &
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
  feed_cpu=0
  ws_cpu=0
  hwm=0
  tick=$(getconf CLK_TCK)
  # CPU seconds of the threads named $1 (utime + stime of /proc/PID/task/*/stat; the name is field 2).
  thread_cpu() {
    # The server may exit between two reads: then the last figure stands.
    { cat /proc/"$server"/task/*/stat 2>/dev/null || true; } |
      awk -v name="($1)" -v t="$tick" '$2 == name { s += $14 + $15 } END { printf "%.2f", s / t }'
  }
  while kill -0 "$server" 2>/dev/null; do
    if stat=$(cat "/proc/$server/stat" 2>/dev/null); then
      cpu=$(echo "$stat" | awk -v t="$tick" '{ printf "%.2f", ($14 + $15) / t }')
      f=$(thread_cpu viewer_feed)
      w=$(thread_cpu viewer_ws)
      # A read after the exit finds no threads (0.00): keep the last real one.
      [ "$f" = 0.00 ] || feed_cpu=$f
      [ "$w" = 0.00 ] || ws_cpu=$w
      hwm=$(awk '/VmHWM/ { print $2 }' "/proc/$server/status" 2>/dev/null || echo "$hwm")
    fi
    sleep 0.5
  done
  wait "$mission" || echo "viewer_load: the mission with $n viewers failed (see $run.log)" >&2
  [ -z "$viewers" ] || wait "$viewers" || true
  ingest=$(jq -c --arg m "$preset" '[.agents[] | select(.mission == $m) | {agent: .agent_id, p50: .ingest_ms.p50, p99: .ingest_ms.p99}]' "$run/server/stats.json")
  mcap_mb=$(du -b "$run/mission.mcap" | awk -v d="$duration" '{ printf "%.2f", $1 / 1e6 / (d / 60) }')
  bandwidth=$( [ -f "$run.viewers.json" ] && tail -1 "$run.viewers.json" || echo null)
  line="{\"viewers\": $n, \"run\": $rep, \"server_cpu_s\": $cpu, \"feed_thread_cpu_s\": $feed_cpu, \"ws_thread_cpu_s\": $ws_cpu, \"server_peak_rss_mb\": $((hwm / 1024)), \"ingest_ms\": $ingest, \"mcap_mb_per_min\": $mcap_mb, \"viewer_traffic\": $bandwidth}"
  echo "$line"
  results+=("$line")
done
done
printf '[%s]\n' "$(IFS=,; echo "${results[*]}")" >"$out/$preset.json"
echo "viewer_load: $out/$preset.json"
