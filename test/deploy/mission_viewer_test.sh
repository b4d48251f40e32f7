#!/usr/bin/env bash
# The live viewer and the recordings on the main job (two agents and the server as separate processes over
# loopback), with real clients:
#  - the reference Foxglove client (test/viewer/client_test.mjs) while the agents fly: wrong and missing tokens
#    refused with 401 and no channel, every channel's messages valid against the foxglove schemas, every agent's
#    pose moving, a merge announced;
#  - the browser viewer in headless Chromium (test/viewer/browser_test.mjs): every agent drawn in its colour; the
#    screenshot is kept as BUILD_DIR/viewer_screenshot.png;
#  - ten more viewers (test/viewer/viewers.mjs), one of which stops reading: the server drops that one's oldest
#    messages (its queue and send buffer are made small here: 16 messages, 64 KiB) and the nine others keep
#    receiving;
#  - after the mission: OUT/mission.mcap (the server's recording) and OUT/maps/maps.mcap (cvislam_mapctl export
#    --mcap) read back alike by @mcap/core and by the project's reader (test/viewer/mcap_check.mjs).
#
#   mission_viewer_test.sh REPO BUILD_DIR MCAP_INTEROP_TOOL
set -euo pipefail
repo=$1
build=$2
mcap_tool=$3
tools=${CVISLAM_DEPLOY_TOOLS:-$repo/out/deploy-tools}
tmp=$(mktemp -d)
mission_pid=""
cleanup() {
  [ -z "$mission_pid" ] || kill -TERM "$mission_pid" 2>/dev/null || true
  [ -z "$mission_pid" ] || wait "$mission_pid" 2>/dev/null || true
  rm -rf "$tmp"
}
trap cleanup EXIT
if pgrep -x iox-roudi >/dev/null; then
  echo "mission_viewer_test: an iox-roudi runs already; this test needs the machine's only one" >&2
  exit 1
fi
[ -d "$tools/node_modules/@foxglove/ws-protocol" ] ||
  { echo "mission_viewer_test: the npm tools are missing in $tools: run deploy/install_deploy_tools.sh" >&2; exit 1; }
CVISLAM_SIM_CACHE="$tmp/cache" timeout 600 "$repo/deploy/run_mission.sh" --build-dir "$build" --duration 30 \
  --no-real --viewer 127.0.0.1:0 --server-arg --viewer-queue --server-arg 16 --server-arg --viewer-send-buffer \
  --server-arg 65536 --out "$tmp/out" >"$tmp/log" 2>&1 &
mission_pid=$!
port=""
while [ -z "$port" ]; do
  kill -0 "$mission_pid" 2>/dev/null || { echo "mission_viewer_test: the mission ended early:" >&2; tail -20 "$tmp/log" >&2; exit 1; }
  port=$(sed -n 's/^viewer on port \([0-9]*\).*/\1/p' "$tmp/out/server.log" 2>/dev/null | head -1) || true
  sleep 0.2
done
token=$(awk '$1 == "overlap2" { print $2 }' "$tmp/out/tokens")
rc=0
node "$repo/test/viewer/client_test.mjs" --port "$port" --mission overlap2 --token "$token" --agents 2 \
  --tools "$tools" --timeout 240 >"$tmp/client.txt" 2>&1 &
client=$!
node "$repo/test/viewer/browser_test.mjs" --url "http://127.0.0.1:$port/?mission=overlap2&token=$token" --agents 2 \
  --screenshot "$build/viewer_screenshot.png" --tools "$tools" --timeout 240 >"$tmp/browser.txt" 2>&1 &
browser=$!
node "$repo/test/viewer/viewers.mjs" --port "$port" --mission overlap2 --token "$token" --clients 10 --stalled 1 \
  --tools "$tools" --seconds 400 >"$tmp/viewers.txt" 2>&1 &
viewers=$!
wait "$client" || rc=1
wait "$browser" || rc=1
echo "foxglove client: $(tail -1 "$tmp/client.txt")"
echo "browser: $(tail -1 "$tmp/browser.txt")"
if ! wait "$mission_pid"; then
  echo "mission_viewer_test: the mission failed; its output ends:" >&2
  tail -30 "$tmp/log" >&2
  rc=1
fi
mission_pid=""
wait "$viewers" || true
echo "ten viewers: $(tail -1 "$tmp/viewers.txt")"
dropped=$(sed -n 's/^viewer: \([0-9]*\) messages dropped.*/\1/p' "$tmp/out/server.log")
if [ -z "$dropped" ] || [ "$dropped" -eq 0 ]; then
  echo "mission_viewer_test: the stalled viewer lost no message (server says '${dropped:-nothing}'): its queue was not bounded" >&2
  rc=1
fi
echo "the stalled viewer: $dropped messages dropped"
reading=$(tail -1 "$tmp/viewers.txt" | jq '[.reading[] | select(.messages_per_s >= 1)] | length' 2>/dev/null || echo 0)
[ "$reading" = 9 ] || { echo "mission_viewer_test: $reading of the 9 reading viewers kept receiving" >&2; rc=1; }
for file in "$tmp/out/mission.mcap:events,stats,keyframes,tf,points,pose,trajectory" \
            "$tmp/out/maps/maps.mcap:keyframes,points,trajectory"; do
  node "$repo/test/viewer/mcap_check.mjs" --file "${file%%:*}" --expect "${file#*:}" --tool "$mcap_tool" \
    --tools "$tools" || rc=1
done
[ "$rc" = 0 ] || { echo "mission_viewer_test: failed; the client said:" >&2; cat "$tmp/client.txt" "$tmp/browser.txt" >&2; }
exit "$rc"
