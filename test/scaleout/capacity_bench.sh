#!/usr/bin/env bash
# Capacity of the scale-out servers: how many agents R replicas keep up with. Every part is a real process on
# loopback: PostgreSQL (deploy/local_postgres.sh), R cvislam_server replicas with place recognition and global BA
# on, and one cvislam_replay per mission streaming a recorded mission's uplinks at real-time rate (the recording:
# the map store a server wrote during a real mission run, e.g. deploy/run_mission.sh's out/mission/store.db). The
# agents come as missions of the recording's size (overlap2: 2 agents), spread over the replicas by the replica
# each mission first contacts. A step keeps up when every batch is acknowledged and the servers' ingest latency
# (a batch's arrival to its stored and applied state, from each replica's stats.json) has its p99 under
# --bound-ms for every agent (the worst agent's p99 is the step's). The agents' acknowledgement latency is reported
# beside it: it includes the downlink's pacing (acknowledgements ride the at most 2 messages per second the server
# sends an agent), so it sits near 500 ms even on an idle server. For each replica count the agent count grows
# until a step does not keep up. Each step runs on a fresh database, so no earlier mission is taken over.
#
#   test/scaleout/capacity_bench.sh BIN_DIR RECORDING [--from-mission M] [--replicas 1,2,3] [--agents 2,4,8,12,16]
#                                   [--seconds 30] [--bound-ms 200] [--out FILE.json] [--server-arg ARG ...]
#
# Prints a table and writes the steps as JSON (default out/bench/capacity.json). All replicas share this machine's
# cores: with R replicas on one machine the figures show the cost of the protocol, not R machines' capacity.
set -euo pipefail
usage() { sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
[ $# -ge 2 ] || usage
bin=$1 recording=$2
shift 2
repo=$(cd "$(dirname "$0")/../.." && pwd)
from_mission=""
replica_counts=1,2,3
agent_counts=2,4,8,12,16
seconds=30
bound_ms=200
out="$repo/out/bench/capacity.json"
server_args=()
while [ $# -gt 0 ]; do
  case "$1" in
    --from-mission) from_mission=$2; shift 2 ;;
    --replicas) replica_counts=$2; shift 2 ;;
    --agents) agent_counts=$2; shift 2 ;;
    --seconds) seconds=$2; shift 2 ;;
    --bound-ms) bound_ms=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --server-arg) server_args+=("$2"); shift 2 ;;
    -h|--help) usage ;;
    *) echo "capacity_bench: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
[ -x "$bin/cvislam_server" ] && [ -x "$bin/cvislam_replay" ] || { echo "capacity_bench: no cvislam_server/cvislam_replay in $bin" >&2; exit 2; }
[ -f "$recording" ] || { echo "capacity_bench: no recording '$recording' (run deploy/run_mission.sh; it writes out/mission/store.db)" >&2; exit 2; }
# The recorded mission and its agent count, from the store's records table.
read -r from_mission per_mission < <(python3 - "$recording" "$from_mission" <<'PY'
import sqlite3, sys
db = sqlite3.connect(f"file:{sys.argv[1]}?mode=ro", uri=True)
rows = db.execute("SELECT mission, count(DISTINCT agent) FROM records WHERE kind = 2 GROUP BY mission ORDER BY 2 DESC, 1").fetchall()
want = sys.argv[2]
pick = [r for r in rows if r[0] == want] if want else rows[:1]
if not pick:
    sys.exit(f"capacity_bench: the recording has no mission '{want}' (it has: {', '.join(r[0] for r in rows)})")
print(pick[0][0], pick[0][1])
PY
)

source "$repo/test/scaleout/lib.sh"
scaleout_work capacity
cpu_s() { awk -v hz="$(getconf CLK_TCK)" '{print ($14 + $15) / hz}' "/proc/$1/stat" 2>/dev/null || echo 0; }

conninfo=$("$repo/deploy/local_postgres.sh" start "$work/pg")
echo "capacity: recording $recording, mission '$from_mission' ($per_mission agents per mission), first $seconds s of" \
  "each agent at real-time rate, bound: ingest p99 <= $bound_ms ms; place recognition and GBA on; $(nproc) cores"
steps=()
IFS=, read -r -a r_list <<< "$replica_counts"
IFS=, read -r -a a_list <<< "$agent_counts"
for R in "${r_list[@]}"; do
  for N in "${a_list[@]}"; do
    missions=$(( (N + per_mission - 1) / per_mission ))
    step="$work/r${R}_a${N}"
    mkdir -p "$step"
    db="cap_r${R}_a${N}"
    psql "$conninfo" -qc "CREATE DATABASE $db" >/dev/null
    ci=${conninfo/dbname=postgres/dbname=$db}
    replica_pids=() ports=()
    for ((r = 0; r < R; r++)); do
      p=$(port); ports+=("$p")
      "$bin/cvislam_server" --listen "127.0.0.1:$p" --postgres "$ci" --replica "r$r" --quiet --output "$step/out$r" \
        "${server_args[@]}" \
        >"$step/replica$r.log" 2>&1 &
      replica_pids+=("$!"); pids+=("$!")
    done
    for ((r = 0; r < R; r++)); do
      wait_for_line "$step/replica$r.log" "listening on" 10 "replica r$r" "${replica_pids[$r]}" || exit 1
    done
    replay_pids=()
    started=$(date +%s.%N)
    for ((m = 0; m < missions; m++)); do
      first=$(( m % R )) list=""
      for ((k = 0; k < R; k++)); do list+="${list:+,}127.0.0.1:${ports[$(( (first + k) % R ))]}"; done
      "$bin/cvislam_replay" --recording "$recording" --from-mission "$from_mission" --server "$list" --mission "m$m" \
        --rate 1 --seconds "$seconds" --flush-timeout 30 --report "$step/m$m.json" >"$step/m$m.log" 2>&1 &
      replay_pids+=("$!"); pids+=("$!")
    done
    replays_ok=1
    for p in "${replay_pids[@]}"; do wait "$p" || replays_ok=0; done
    wall=$(python3 -c "import time;print(round(time.time() - $started, 1))")
    cpu=0
    for p in "${replica_pids[@]}"; do cpu=$(python3 -c "print($cpu + $(cpu_s "$p"))"); done
    for p in "${replica_pids[@]}"; do kill -INT "$p" 2>/dev/null || true; done
    for p in "${replica_pids[@]}"; do wait "$p" 2>/dev/null || true; done
    line=$(python3 - "$step" "$missions" "$R" "$N" "$bound_ms" "$wall" "$cpu" "$replays_ok" <<'PY'
import json, sys
step, missions, R, N, bound, wall, cpu, ok = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5]), float(sys.argv[6]), float(sys.argv[7]), sys.argv[8] == "1"
agents = []
for m in range(missions):
    try:
        agents += json.load(open(f"{step}/m{m}.json"))["agents"]
    except (OSError, ValueError, KeyError):
        ok = False
ack = sorted(x for a in agents for x in a.get("ack_ms", []))
served = []  # the servers' view: one entry per (mission, agent) a replica served
for r in range(R):
    try:
        served += [a for a in json.load(open(f"{step}/out{r}/stats.json"))["agents"] if int(a["ingest_ms"]["samples"]) > 0]
    except (OSError, ValueError, KeyError):
        ok = False
def median(v): return sorted(v)[len(v) // 2] if v else None
finished = ok and bool(agents) and all(a["finished"] for a in agents) and len(served) >= len(agents)
ingest_p99 = max((a["ingest_ms"]["p99"] for a in served), default=float("inf"))
gba = [a["ingest_during_gba_ms"] for a in served if int(a["ingest_during_gba_ms"]["samples"]) > 0]
row = {"replicas": R, "agents": len(agents), "missions": missions, "finished": bool(finished),
       "ingest_ms_p50_median": median([a["ingest_ms"]["p50"] for a in served]), "ingest_ms_p99_worst": ingest_p99,
       "ingest_during_gba_ms_p99_worst": max((g["p99"] for g in gba), default=None),
       "ingest_during_gba_samples": sum(int(g["samples"]) for g in gba),
       "ack_ms_p50": ack[len(ack) // 2] if ack else None, "ack_ms_p99": ack[int(0.99 * (len(ack) - 1))] if ack else None,
       "batches": sum(a["batches"] for a in agents), "acked": sum(a["acked"] for a in agents),
       "redirects": sum(a["redirects"] for a in agents), "wall_s": wall, "server_cpu_s": round(cpu, 1),
       "keeps_up": bool(finished and ingest_p99 <= bound)}
print(json.dumps(row))
PY
)
    steps+=("$line")
    python3 -c "
import json,sys; r=json.loads(sys.argv[1])
f = lambda v: '-' if v is None else f'{v:.0f}'
print(f\"replicas {r['replicas']}  agents {r['agents']:3d} ({r['missions']} missions)  acked {r['acked']}/{r['batches']}  \"
      f\"ingest p50 {f(r['ingest_ms_p50_median'])} ms  p99 {f(r['ingest_ms_p99_worst'])} ms (during GBA {f(r['ingest_during_gba_ms_p99_worst'])})  \"
      f\"ack p50/p99 {f(r['ack_ms_p50'])}/{f(r['ack_ms_p99'])} ms  server CPU {r['server_cpu_s']} s in {r['wall_s']} s  \"
      f\"{'keeps up' if r['keeps_up'] else 'DOES NOT KEEP UP'}\")" "$line"
    keeps=$(python3 -c "import json,sys;print(int(json.loads(sys.argv[1])['keeps_up']))" "$line")
    [ "$keeps" = 1 ] || break
  done
done
mkdir -p "$(dirname "$out")"
python3 - "$out" "$recording" "$from_mission" "$seconds" "$bound_ms" "${steps[@]}" <<'PY'
import json, sys, os
out, recording, mission, seconds, bound = sys.argv[1:6]
steps = [json.loads(s) for s in sys.argv[6:]]
best = {}
for s in steps:
    if s["keeps_up"]:
        best[s["replicas"]] = max(best.get(s["replicas"], 0), s["agents"])
json.dump({"recording": recording, "mission": mission, "seconds": float(seconds), "bound_ms_p99": float(bound),
           "cores": os.cpu_count(), "steps": steps, "agents_kept_up": {str(k): v for k, v in best.items()}},
          open(out, "w"), indent=2)
print("agents kept up with: " + ", ".join(f"{r} replica(s): {n}" for r, n in sorted(best.items())) + f"  ({out})")
PY
