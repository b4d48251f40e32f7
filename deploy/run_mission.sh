#!/usr/bin/env bash
# The project's main job: a collaborative mission, end to end. It installs what is missing, builds, renders a
# simulated multi-agent mission once (cached), starts an iceoryx RouDi, cvislam_server on loopback and one
# cvislam_agent process per agent, waits for them, has the server write what it holds, and prints the result
# tables; then one agent on the real EuRoC V1_01 excerpt through the same server; then it reads the maps back
# through the map service (cvislam_mapctl), as an API client would.
#
#   deploy/run_mission.sh [--preset NAME] [--seed N] [--duration SEC] [--mode stereo|mono] [--pace realtime|sync]
#                         [--out DIR] [--build-dir DIR] [--no-real] [--server-arg ARG ...] [--agent-config FILE]
#                         [--viewer HOST:PORT | --no-viewer] [--hold]
#
#   --preset    a cvislam_sim preset: overlap2 (default; 2 agents), loop, hall4, hall8, aggressive, or euroc-mh
#               (the five real EuRoC Machine Hall flights, replayed by the simulator in one world frame)
#   --seed      simulator seed [1]
#   --duration  seconds per agent [the preset's: 60; euroc-mh: 90]
#   --mode      stereo (default) or mono (mono-inertial)
#   --pace      sync (default: after each keyframe tracking waits for mapping, so every run gives the same
#               figures on a loaded machine) or realtime (frames at the sensor rate, as on a robot; on this
#               2-core machine several realtime agents compete for the cores, see docs/agent.md)
#   --out       results [out/mission]: summary.json, report/index.html, server/, agents/, eval/, maps/
#   --no-real   skip the agent on the real EuRoC excerpt
#   --server-arg one more cvislam_server argument, repeatable (e.g. --server-arg --no-gba)
#   --agent-config a cvislam_agent YAML config for the mission's agents (deploy/agent_config.yaml shows every
#               key; e.g. one with link: apply_corrections: true); command-line options still win
#   --agents    fly only these of the preset's agents, by number, comma-separated (e.g. --agents 0,1 for
#               euroc-mh's MH_01 and MH_02); they keep their numbers and trajectories [all]
#   --no-store  the server keeps its maps in memory only (default: a map store, out/.../store.db, that makes
#               every batch durable before it is acknowledged)
#   --trace     the server and every agent write a Chrome trace (OUT/trace/); cvislam_trace joins them into
#               OUT/trace/mission_trace.json (open it in https://ui.perfetto.dev) and prints the latency of each
#               link of a keyframe's way, from the camera to the server and back (OUT/trace/chain.json)
#   --metrics   the server serves Prometheus metrics on a free loopback port (printed); after the agents end they
#               are scraped once into OUT/server/metrics.txt
#   --viewer    where the server serves the live viewer [127.0.0.1:8765, or a free port when that one is taken;
#               port 0 takes a free one]: open the printed http://... address in a browser while the mission runs,
#               or connect Foxglove/Lichtblick to the printed ws://... address. The mission is also recorded into
#               OUT/mission.mcap either way
#   --no-viewer no live viewer (the recording is still written)
#   --hold      after the agents end, keep the server (and the viewer) up until Ctrl-C or SIGTERM, then finish as
#               usual (the server's final GBA, its outputs, the report)
#   --kill-server N  the restart test: kill the server with SIGKILL N times at random moments (2-8 s apart,
#               --kill-seed S, default 1) while the agents fly, and start it again on its store at once; the
#               kills, the replays and the time until every agent streams again go to restarts.csv and the end
#
# Environment: CVISLAM_DATA_DIR (default ../shared/data beside the repository) for the real data and the
# euroc-mh flights; CVISLAM_SIM_CACHE (default out/sim-cache) for rendered missions.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$repo/deploy/lib/wait.sh"
preset=overlap2
seed=1
duration=""
mode=stereo
pace=sync
out="$repo/out/mission"
build="$repo/build/default"
real=1
server_args=()
agent_args=()
only_agents=""
store=1
kills=0
kill_seed=1
trace=0
metrics=0
viewer=default
hold=0
while [ $# -gt 0 ]; do
  case "$1" in
    --preset) preset=$2; shift 2 ;;
    --seed) seed=$2; shift 2 ;;
    --duration) duration=$2; shift 2 ;;
    --mode) mode=$2; shift 2 ;;
    --pace) pace=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --build-dir) build=$2; shift 2 ;;
    --no-real) real=0; shift ;;
    --server-arg) server_args+=("$2"); shift 2 ;;
    --agent-config)
      [ -f "$2" ] || { echo "run_mission: --agent-config: no such file '$2'" >&2; exit 2; }
      agent_args=(--config "$(cd "$(dirname "$2")" && pwd)/$(basename "$2")"); shift 2 ;;
    --agents) only_agents=$2; shift 2 ;;
    --no-store) store=0; shift ;;
    --kill-server) kills=$2; shift 2 ;;
    --kill-seed) kill_seed=$2; shift 2 ;;
    --trace) trace=1; shift ;;
    --metrics) metrics=1; shift ;;
    --viewer) viewer=$2; shift 2 ;;
    --no-viewer) viewer=""; shift ;;
    --hold) hold=1; shift ;;
    -h|--help) awk 'NR > 1 && /^set -euo/ { exit } NR > 1' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "run_mission: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
case "$mode" in stereo|mono) ;; *) echo "run_mission: --mode must be stereo or mono, not '$mode'" >&2; exit 2 ;; esac
case "$pace" in realtime|sync) ;; *) echo "run_mission: --pace must be realtime or sync, not '$pace'" >&2; exit 2 ;; esac
[[ -z "$only_agents" || "$only_agents" =~ ^[0-9]+(,[0-9]+)*$ ]] ||
  { echo "run_mission: --agents must be agent numbers separated by commas (e.g. 0,1), not '$only_agents'" >&2; exit 2; }
[[ "$seed" =~ ^[0-9]+$ ]] || { echo "run_mission: --seed must be a whole number, not '$seed'" >&2; exit 2; }
[[ "$kills" =~ ^[0-9]+$ && "$kill_seed" =~ ^[0-9]+$ ]] ||
  { echo "run_mission: --kill-server and --kill-seed must be whole numbers" >&2; exit 2; }
[ "$kills" -eq 0 ] || [ "$store" = 1 ] ||
  { echo "run_mission: --kill-server needs the map store (drop --no-store)" >&2; exit 2; }
if [ -z "$duration" ]; then
  if [ "$preset" = euroc-mh ]; then duration=90; else duration=60; fi
fi
[[ "$duration" =~ ^[0-9]+([.][0-9]+)?$ ]] || { echo "run_mission: --duration must be seconds, not '$duration'" >&2; exit 2; }

t_start=$(date +%s)
"$repo/deploy/install_deps.sh"

echo "== build (preset 'default' in $build)"
if [ ! -f "$build/build.ninja" ]; then
  cmake -S "$repo" --preset default -B "$build" >/dev/null
fi
cmake --build "$build" --target cvislam_sim cvislam_server cvislam_agent cvislam_eval cvislam_mapctl cvislam_trace
bin="$build/bin"
t_built=$(date +%s)

data=${CVISLAM_DATA_DIR:-"$repo/../shared/data"}
if [ "$preset" = euroc-mh ] && [ ! -d "$data/euroc-groundtruth" ]; then
  echo "run_mission: the euroc-mh preset replays the EuRoC flights in $data/euroc-groundtruth, which is missing;" >&2
  echo "  set CVISLAM_DATA_DIR to the shared data folder, or choose another --preset" >&2
  exit 1
fi
export CVISLAM_DATA_DIR="$data"

# 1. The simulated mission, rendered once per preset, seed, duration and plan (stereo: mono runs use cam0 only).
#    The plan's fingerprint (hall, obstacles, paths) is in the folder's name, so a changed preset renders anew.
cache_root=${CVISLAM_SIM_CACHE:-"$repo/out/sim-cache"}
fingerprint=$("$bin/cvislam_sim" --preset "$preset" --seed "$seed" --duration "$duration" --fingerprint) ||
  { echo "run_mission: cvislam_sim could not plan preset $preset (see above)" >&2; exit 1; }
cache="$cache_root/$preset-seed$seed-${duration}s-$fingerprint"
if [ ! -f "$cache/.complete" ]; then
  echo "== render $preset (seed $seed, $duration s per agent) into $cache (once; later runs reuse it)"
  rm -rf "$cache" "$cache.partial"
  mkdir -p "$cache_root"
  "$bin/cvislam_sim" --preset "$preset" --seed "$seed" --duration "$duration" --stereo --out "$cache.partial" \
    | awk '/frames,/ { if (++n % 2 == 0) { print; fflush() } next } { print; fflush() }'
  mv "$cache.partial" "$cache"
  touch "$cache/.complete"
else
  echo "== mission $preset (seed $seed, $duration s) from the cache: $cache"
fi
t_rendered=$(date +%s)
agents=()
for d in "$cache"/agent*; do [ -d "$d/mav0" ] && agents+=("$(basename "$d")"); done
[ "${#agents[@]}" -gt 0 ] || { echo "run_mission: no agents in $cache" >&2; exit 1; }
if [ -n "$only_agents" ]; then
  chosen=()
  for id in ${only_agents//,/ }; do
    [ -d "$cache/agent$id/mav0" ] ||
      { echo "run_mission: --agents names agent$id, but preset $preset has only: ${agents[*]}" >&2; exit 2; }
    chosen+=("agent$id")
  done
  agents=("${chosen[@]}")
fi

rm -rf "$out"
mkdir -p "$out/agents" "$out/server" "$out/eval"
mission="$preset"

# 2. RouDi (one per machine: the agents share it), the server, the agents. Everything stops on exit.
pids=()
roudi_pid=""
server_pid=""
cleanup() {
  for p in "${pids[@]}"; do kill -TERM "$p" 2>/dev/null || true; done
  [ -n "$server_pid" ] && kill -TERM "$server_pid" 2>/dev/null || true
  # The agents and the server first, by pid: a bare `wait` would also wait for RouDi, which runs until told to stop,
  # and hang an early exit (a server that would not start) with RouDi left behind for the next run.
  for p in "${pids[@]}" ${server_pid:+"$server_pid"}; do wait "$p" 2>/dev/null || true; done
  [ -n "$roudi_pid" ] && kill -TERM "$roudi_pid" 2>/dev/null && wait "$roudi_pid" 2>/dev/null || true
}
trap cleanup EXIT
trap 'echo "run_mission: interrupted" >&2; exit 130' INT TERM

if pgrep -x iox-roudi >/dev/null; then
  echo "run_mission: an iox-roudi is running already (pid $(pgrep -x iox-roudi | tr '\n' ' ')); iceoryx allows one per" >&2
  echo "  machine and this mission starts its own: stop it first (kill -TERM <pid>)" >&2
  exit 1
fi
iox-roudi -m off -c "$repo/deploy/roudi_config.toml" >"$out/roudi.log" 2>&1 &
roudi_pid=$!
wait_for_line "$out/roudi.log" "RouDi is ready" 10 iox-roudi "$roudi_pid" || exit 1

store_args=()
[ "$store" = 1 ] && store_args=(--store "$out/store.db")
# Every mission has its token (the server's tokens file, readable by this user only): the agents and the map
# service client present it, as a deployment's would (CVISLAM_TOKEN keeps it out of the process list).
new_token() { od -An -N16 -tx1 /dev/urandom | tr -d ' \n'; }
mission_token=$(new_token)
real_token=$(new_token)
(umask 077; printf '%s %s\neuroc-v101 %s\n' "$mission" "$mission_token" "$real_token" >"$out/tokens")
store_args+=(--tokens "$out/tokens")
trace_dir="$out/trace"
if [ "$trace" = 1 ]; then
  mkdir -p "$trace_dir"
  store_args+=(--trace "$trace_dir/server.json")
fi
[ "$metrics" = 0 ] || store_args+=(--metrics-listen 127.0.0.1:0)
# The live viewer, and every mission recorded as MCAP (the simulated one becomes OUT/mission.mcap at the end).
store_args+=(--record "$out/recordings")
if [ "$viewer" = default ]; then
  # 8765 unless something listens there already (another mission held open, say): then any free port.
  viewer=127.0.0.1:8765
  if (exec 3<>/dev/tcp/127.0.0.1/8765) 2>/dev/null; then
    echo "run_mission: port 8765 is taken; the viewer takes a free port (printed below)"
    viewer=127.0.0.1:0
  fi
fi
if [ -n "$viewer" ]; then
  # The page draws with three.js from npm (deploy/install_deploy_tools.sh puts it in out/deploy-tools).
  tools=${CVISLAM_DEPLOY_TOOLS:-"$repo/out/deploy-tools"}
  if [ ! -f "$tools/node_modules/three/build/three.module.js" ]; then
    "$repo/deploy/install_deploy_tools.sh" >/dev/null ||
      echo "run_mission: could not install three.js (deploy/install_deploy_tools.sh); the viewer page will not draw" >&2
  fi
  store_args+=(--viewer-listen "$viewer" --viewer-three "$tools/node_modules/three/build")
fi
# Starts the server on $1 (host:port) and waits until it serves (after replaying its store).
start_server() {
  rm -f "$out/server.port"
  "$bin/cvislam_server" --listen "$1" --port-file "$out/server.port" --output "$out/server" \
    --status-interval 10 ${store_args[@]+"${store_args[@]}"} ${server_args[@]+"${server_args[@]}"} >"$out/server.log" 2>&1 &
  server_pid=$!
  wait_for_file "$out/server.port" 30 cvislam_server "$server_pid" "$out/server.log" || exit 1
}
start_server 127.0.0.1:0
port=$(cat "$out/server.port")
[ "$metrics" = 0 ] || echo "== metrics: $(grep -m1 '^metrics on port' "$out/server.log")"
if [ -n "$viewer" ]; then
  viewer_port=$(sed -n 's/^viewer on port \([0-9]*\).*/\1/p' "$out/server.log" | head -1)
  viewer_host=${viewer%:*}
  [ "$viewer_host" = 0.0.0.0 ] && viewer_host=$(hostname)
  echo "== live viewer: http://$viewer_host:$viewer_port/?mission=$mission&token=$mission_token"
  echo "   (Foxglove or Lichtblick: open ws://$viewer_host:$viewer_port/?mission=$mission&token=$mission_token)"
fi
echo "== mission '$mission': server on 127.0.0.1:$port, ${#agents[@]} agent(s), $mode-inertial, pace $pace," \
  "$([ "$store" = 1 ] && echo "map store $out/store.db" || echo "no map store"), mission tokens in $out/tokens"

# The restart test's schedule: kill k at kill_at[k] seconds after the agents start (seeded).
kill_at=()
if [ "$kills" -gt 0 ]; then
  RANDOM=$kill_seed
  t_kill=0
  for _ in $(seq "$kills"); do t_kill=$((t_kill + 2 + RANDOM % 7)); kill_at+=("$t_kill"); done
  echo "kill,at_s,replay_s,serving_s,all_agents_streaming_s,keyframes_replayed" >"$out/restarts.csv"
  echo "== restart test: the server is killed (SIGKILL) at ${kill_at[*]} s and started again on its store"
fi
# True once the server's log has $1 agents "connected; it resumes".
# shellcheck disable=SC2317  # called through wait_until
resumed() { [ "$(grep -c 'connected; it resumes' "$out/server.log" || true)" -ge "$1" ]; }
# Kills the server, starts it again on the same port and store, and times it (one line of restarts.csv).
restart_server() {
  local k=$1 t0 t1 now replayed serving streaming
  t0=$(date +%s.%N)
  kill -KILL "$server_pid"
  wait "$server_pid" 2>/dev/null || true
  mv "$out/server.log" "$out/server.killed$k.log"
  start_server "127.0.0.1:$port"
  t1=$(date +%s.%N)
  # Every agent still flying has connected again when the new server has one "connected" line per agent; the
  # time stands in restarts.csv even when one has not within 20 s.
  local flying=0
  for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && flying=$((flying + 1)); done
  wait_until 20 "$flying agent(s) to stream to the restarted server" resumed "$flying" || true
  now=$(date +%s.%N)
  replayed=$(sed -n 's/.*replayed.*missions, \([0-9]*\) keyframes, in \([0-9.]*\) s/\1 \2/p' "$out/server.log")
  serving=$(awk "BEGIN { print $t1 - $t0 }")
  streaming=$(awk "BEGIN { print $now - $t0 }")
  echo "$k,${kill_at[$((k - 1))]},${replayed#* },$serving,$streaming,${replayed%% *}" >>"$out/restarts.csv"
  printf '  kill %d at %s s: serving again after %.2f s, every agent streaming after %.2f s (%s keyframes replayed)\n' \
    "$k" "${kill_at[$((k - 1))]}" "$serving" "$streaming" "${replayed%% *}"
}

for a in "${agents[@]}"; do
  id=${a#agent}
  trace_args=()
  if [ "$trace" = 1 ]; then trace_args=(--trace "$trace_dir/$a.json"); fi
  CVISLAM_TOKEN="$mission_token" "$bin/cvislam_agent" --dataset "$cache/$a" --output "$out/agents/$a" --roudi external --agent-id "$id" \
    --server "127.0.0.1:$port" --mission "$mission" --mode "$mode" --pace "$pace" ${agent_args[@]+"${agent_args[@]}"} \
    ${trace_args[@]+"${trace_args[@]}"} \
    >"$out/agents/$a.log" 2>&1 &
  pids+=("$!")
done
t_agents=$(date +%s)
# Progress: every 10 s, each agent's newest progress line; the restart test's kills when they are due.
failed=0
next_kill=0
ticks=0
while true; do
  running=0
  for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && running=$((running + 1)); done
  [ "$running" -eq 0 ] && break
  sleep 0.5
  ticks=$((ticks + 1))
  if [ "$next_kill" -lt "${#kill_at[@]}" ] && [ $(( $(date +%s) - t_agents )) -ge "${kill_at[$next_kill]}" ]; then
    next_kill=$((next_kill + 1))
    restart_server "$next_kill"
  fi
  [ $((ticks % 20)) -eq 0 ] || continue
  for a in "${agents[@]}"; do
    line=$(grep -a '^\[agent\] frame' "$out/agents/$a.log" | tail -1 | sed 's/^\[agent\] //') || true
    [ -n "$line" ] && printf '  %-7s %s\n' "$a" "$line"
  done
done
if [ "$kills" -gt 0 ] && [ "$next_kill" -lt "$kills" ]; then
  echo "  the agents finished after $next_kill of the $kills kills" >&2
fi
for i in "${!pids[@]}"; do
  if ! wait "${pids[$i]}"; then
    echo "run_mission: ${agents[$i]} failed; its log ends:" >&2
    tail -5 "$out/agents/${agents[$i]}.log" >&2
    failed=1
  fi
done
pids=()
t_ran=$(date +%s)

# 3. One agent on real images through the same server: the EuRoC V1_01 excerpt (4.7 s, stereo-inertial).
if [ "$real" = 1 ] && [ -d "$data/euroc-v101-excerpt/mav0" ]; then
  echo "== real data: one agent on the EuRoC V1_01 excerpt, mission 'euroc-v101'"
  CVISLAM_TOKEN="$real_token" "$bin/cvislam_agent" --dataset "$data/euroc-v101-excerpt" --output "$out/agents/real_v101" --roudi external \
    --agent-id 0 --server "127.0.0.1:$port" --mission euroc-v101 --mode stereo --pace sync \
    >"$out/agents/real_v101.log" 2>&1 || { echo "run_mission: the real-data agent failed:" >&2; tail -5 "$out/agents/real_v101.log" >&2; failed=1; }
elif [ "$real" = 1 ]; then
  echo "== real data: SKIPPED ($data/euroc-v101-excerpt not found; set CVISLAM_DATA_DIR)"
fi

# 4. The map service, as an API client sees it: the mission's maps, their files (PLY points, TUM keyframes, a JSON
#    summary) and its events so far, in $out/maps. Read while the server runs, so before its final GBA.
if [ "$metrics" = 1 ]; then
  metrics_port=$(sed -n 's/^metrics on port \([0-9]*\).*/\1/p' "$out/server.log" | tail -1)
  mkdir -p "$out/server"
  if curl -sf "http://127.0.0.1:$metrics_port/metrics" -o "$out/server/metrics.txt"; then
    echo "== metrics: http://127.0.0.1:$metrics_port/metrics, scraped into $out/server/metrics.txt"
  else
    echo "run_mission: the metrics endpoint on port '$metrics_port' did not answer" >&2; failed=1
  fi
fi
echo "== map service (cvislam_mapctl; the maps before the server's final GBA, files in $out/maps)"
export CVISLAM_TOKEN="$mission_token"
if "$bin/cvislam_mapctl" --server "127.0.0.1:$port" maps "$mission" >"$out/maps.txt" 2>&1 &&
   "$bin/cvislam_mapctl" --server "127.0.0.1:$port" export "$mission" --out "$out/maps" >>"$out/maps.txt" 2>&1 &&
   "$bin/cvislam_mapctl" --server "127.0.0.1:$port" watch "$mission" --from 1 --seconds 1 >"$out/maps/events.txt" 2>&1; then
  sed -n '2,$p' "$out/maps.txt" | grep -v ' bytes ' | sed 's/^/  /'
  echo "  $(grep -c '^#' "$out/maps/events.txt") map events so far (cvislam_mapctl watch): $(grep -c 'keyframe added' "$out/maps/events.txt") keyframes added, $(grep -c 'maps merged' "$out/maps/events.txt") merges, $(grep -c 'map corrected' "$out/maps/events.txt") corrections, $(grep -c 'keyframe removed' "$out/maps/events.txt") removals; in maps/events.txt"
else
  echo "run_mission: the map service failed:" >&2; cat "$out/maps.txt" >&2; failed=1
fi

if "$bin/cvislam_mapctl" --server "127.0.0.1:$port" export "$mission" --mcap "$out/maps/maps.mcap" >>"$out/maps.txt" 2>&1; then
  echo "  $(tail -1 "$out/maps.txt")"
else
  echo "run_mission: cvislam_mapctl export --mcap failed:" >&2; tail -3 "$out/maps.txt" >&2; failed=1
fi

if [ "$hold" = 1 ]; then
  echo "== holding the server (and the viewer) until Ctrl-C (or SIGTERM to this script, pid $$); then it finishes"
  held=1
  trap 'held=0' INT TERM
  while [ "$held" = 1 ] && kill -0 "$server_pid" 2>/dev/null; do sleep 1; done
  trap 'echo "run_mission: interrupted" >&2; exit 130' INT TERM
fi
kill -TERM "$server_pid"
wait "$server_pid" || { echo "run_mission: cvislam_server failed:" >&2; tail -5 "$out/server.log" >&2; failed=1; }
if [ -f "$out/recordings/$mission.mcap" ]; then
  mv "$out/recordings/$mission.mcap" "$out/mission.mcap"
  echo "== recording: $out/mission.mcap ($(du -h "$out/mission.mcap" | cut -f1); open it in Foxglove or Lichtblick)"
else
  echo "run_mission: the server wrote no recording of mission $mission" >&2; failed=1
fi
server_pid=""
kill -TERM "$roudi_pid" 2>/dev/null || true
wait "$roudi_pid" 2>/dev/null || true
roudi_pid=""
t_done=$(date +%s)

if [ "$trace" = 1 ]; then
  echo "== traces: a keyframe's way from the camera to the server and back (cvislam_trace merge)"
  traces=("$trace_dir/server.json")
  for a in "${agents[@]}"; do [ -f "$trace_dir/$a.json" ] && traces+=("$trace_dir/$a.json"); done
  "$bin/cvislam_trace" merge --output "$trace_dir/mission_trace.json" --json "$trace_dir/chain.json" "${traces[@]}" |
    tee "$trace_dir/chain.txt" | sed 's/^/  /' || { echo "run_mission: cvislam_trace failed" >&2; failed=1; }
fi

# The restart test's verdict: per agent, the keyframes it made against those the last server holds, keyframes
# held twice across the exported maps, and batches a restarted server had acknowledged but no longer held.
if [ "$kills" -gt 0 ]; then
  echo "== restart test: $next_kill kills (seed $kill_seed), restarts.csv"
  for a in "${agents[@]}"; do
    id=${a#agent}
    made=$(grep -vc '^#' "$out/agents/$a/keyframes.txt" || true)
    held=$(jq -r --argjson id "$id" --arg m "$mission" \
      '[.agents[] | select(.agent_id == $id and .mission == $m) | .keyframes | tonumber] | add // 0' "$out/server/stats.json")
    twice=$(cat "$out/maps/keyframes_agent${id}"_map*.txt 2>/dev/null | grep -v '^#' | awk '{ print $1 }' | sort | uniq -d | wc -l)
    lost=$(jq -r '.acked_batches_lost' "$out/agents/$a/link.json")
    streams=$(jq -r '.connections' "$out/agents/$a/link.json")
    echo "  $a: $made keyframes made, $held held by the server, $twice held twice, $lost acknowledged batches lost, $streams streams"
  done
fi

cat >"$out/mission.json" <<EOF
{"preset": "$preset", "seed": $seed, "duration_s": $duration, "mode": "$mode", "pace": "$pace",
 "mission": "$mission", "dataset": "$cache", "agents": [$(printf '"%s",' "${agents[@]}" | sed 's/,$//')],
 "real_data": "$data/euroc-v101-excerpt",
 "wall_s": {"build": $((t_built - t_start)), "render": $((t_rendered - t_built)), "mission": $((t_ran - t_agents)),
            "total_until_report": $((t_done - t_start))}}
EOF

# 5. Scores, tables, summary.json and the report with pictures.
/usr/bin/python3 "$repo/tools/mission_report.py" --out "$out" --eval "$bin/cvislam_eval"
echo
echo "wall time: build $((t_built - t_start)) s, render $((t_rendered - t_built)) s, mission $((t_ran - t_agents)) s," \
  "total $(( $(date +%s) - t_start )) s"
echo "results: $out (summary.json; open report/index.html in a browser)"
exit "$failed"
