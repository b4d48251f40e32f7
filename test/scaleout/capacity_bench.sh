#!/usr/bin/env bash
# Capacity of the scale-out servers: how many agents R replicas keep up with. Every part is a real process on
# loopback: PostgreSQL (deploy/local_postgres.sh), R cvislam_server replicas with place recognition and global BA
# on, and one cvislam_replay per mission streaming a recorded mission's uplinks at real-time rate (the recording:
# the map store a server wrote during a real mission run, e.g. deploy/run_mission.sh's out/mission/store.db). The
# agents come as missions of the recording's size (overlap2: 2 agents), or with --copies K of K times its size
# (each recorded agent flown K times under new ids, in world frames of their own), or with --one-mission as a
# single mission of all of them; missions spread over the replicas by the replica each first contacts. A step
# keeps up when every batch is acknowledged and the servers' ingest latency (a batch's arrival to its stored and
# applied state, from each replica's stats.json) has its p99 under --bound-ms for every agent (the worst agent's
# p99 is the step's; the p99 pooled over every batch of every replica, from their ingest_ms.csv, is beside it).
# The agents' acknowledgement latency is reported too: it includes the downlink's pacing (acknowledgements ride
# the at most 2 messages per second the server sends an agent), so it sits near 500 ms even on an idle server.
# For each replica count the agent count grows until a step does not keep up. Each step runs on a fresh database.
#
# --replica-cpus C runs each replica in a cgroup of its own with a budget of C cores (and PostgreSQL and the
# replay clients in theirs, --postgres-cpus and --client-cpus, unlimited by default), so that R replicas stand for
# R machines of C cores on one machine; the steps then report each replica's cpu.stat (periods throttled) and how
# much of the budget was used. Needs root and the cgroup cpu controller (v1 or v2). Without it all replicas share
# this machine's cores, and the figures show the protocol's cost, not R machines' capacity.
#
#   test/scaleout/capacity_bench.sh BIN_DIR RECORDING [--from-mission M] [--replicas 1,2,3] [--agents 2,4,8,12,16]
#       [--seconds 30] [--bound-ms 200] [--copies K | --one-mission] [--copy-delay S] [--replica-cpus C]
#       [--postgres-cpus C] [--client-cpus C] [--keep-going] [--out FILE.json] [--server-arg ARG ...]
#
# Prints a line per step and writes the steps as JSON (default out/bench/capacity.json), with every batch's
# ingest time. --keep-going runs every agent count even after a step fails.
set -euo pipefail
usage() { sed -n '2,30p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
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
copies=1 copy_delay=1 one_mission=0 keep_going=0
replica_cpus=0 postgres_cpus=0 client_cpus=0
number() { python3 -c "import sys; v = float(sys.argv[1]); sys.exit(0 if v >= 0 else 1)" "$2" 2>/dev/null ||
  { echo "capacity_bench: $1 takes a number >= 0, got '$2'" >&2; exit 2; }; }
while [ $# -gt 0 ]; do
  case "$1" in
    --copies) copies=$2; shift 2 ;;
    --copy-delay) number "$1" "$2"; copy_delay=$2; shift 2 ;;
    --one-mission) one_mission=1; shift ;;
    --keep-going) keep_going=1; shift ;;
    --replica-cpus) number "$1" "$2"; replica_cpus=$2; shift 2 ;;
    --postgres-cpus) number "$1" "$2"; postgres_cpus=$2; shift 2 ;;
    --client-cpus) number "$1" "$2"; client_cpus=$2; shift 2 ;;
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
[[ "$copies" =~ ^[1-9][0-9]*$ ]] || { echo "capacity_bench: --copies takes a whole number >= 1, got '$copies'" >&2; exit 2; }
[ "$one_mission" = 0 ] || [ "$copies" = 1 ] || { echo "capacity_bench: --one-mission sets the copies itself: drop --copies" >&2; exit 2; }
budgets=$(python3 -c "print(int(float('$replica_cpus') > 0))")
[ "$budgets" = 1 ] || [ "$postgres_cpus$client_cpus" = 00 ] ||
  { echo "capacity_bench: --postgres-cpus and --client-cpus go with --replica-cpus" >&2; exit 2; }
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

# The machine's busy and total jiffies (all cores, /proc/stat): a step whose machine was near 1.0 busy measured
# the machine, not the replicas' budgets.
machine_cpu() { awk '/^cpu / {idle = $5 + $6; total = 0; for (i = 2; i <= NF; i++) total += $i; print total - idle, total}' /proc/stat; }
rss_mb() { awk '/^VmHWM:/ {print $2 / 1024}' "/proc/$1/status" 2>/dev/null || echo 0; }

if [ "$budgets" = 1 ]; then
  cgroup_init "cvislam-capacity-$$" || exit 2
  cgroup_make postgres "$postgres_cpus"
  cgroup_make clients "$client_cpus"
fi
conninfo=$("$repo/deploy/local_postgres.sh" start "$work/pg")
if [ "$budgets" = 1 ]; then
  # The postmaster and the processes it has; the backends it forks for later connections follow it.
  pg_main=$(head -1 "$work/pg/data/postmaster.pid")
  cgroup_move postgres "$pg_main" $(pgrep -P "$pg_main")
fi
budget_text="no CPU budgets (every process shares the $(nproc) cores)"
[ "$budgets" = 1 ] && budget_text="each replica in $replica_cpus cores (cgroup v$cgroup_v, period $((cgroup_period_us / 1000)) ms), PostgreSQL in ${postgres_cpus/#0/unlimited}, the clients in ${client_cpus/#0/unlimited}"
echo "capacity: recording $recording, mission '$from_mission' ($per_mission agents), copies $([ "$one_mission" = 1 ] && echo "as many as one mission needs" || echo "$copies"), first $seconds s of" \
  "each agent at real-time rate, bound: ingest p99 <= $bound_ms ms; place recognition and GBA on; $budget_text"
steps=()
IFS=, read -r -a r_list <<< "$replica_counts"
IFS=, read -r -a a_list <<< "$agent_counts"
for R in "${r_list[@]}"; do
  for N in "${a_list[@]}"; do
    step_copies=$copies
    [ "$one_mission" = 1 ] && step_copies=$(( (N + per_mission - 1) / per_mission ))
    missions=$(( (N + per_mission * step_copies - 1) / (per_mission * step_copies) ))
    step="$work/r${R}_a${N}"
    mkdir -p "$step"
    db="cap_r${R}_a${N}"
    psql "$conninfo" -qc "CREATE DATABASE $db" >/dev/null
    ci=${conninfo/dbname=postgres/dbname=$db}
    replica_pids=() ports=()
    for ((r = 0; r < R; r++)); do
      p=$(port); ports+=("$p")
      replica=("$bin/cvislam_server" --listen "127.0.0.1:$p" --postgres "$ci" --replica "r$r" --quiet
        --output "$step/out$r" "${server_args[@]}")
      run_budgeted "r${R}_a${N}_replica$r" "$replica_cpus" "$step/replica$r.log" "${replica[@]}"
      replica_pids+=("$started_pid"); pids+=("$started_pid")
    done
    for ((r = 0; r < R; r++)); do
      wait_for_line "$step/replica$r.log" "listening on" 10 "replica r$r" "${replica_pids[$r]}" || exit 1
    done
    replay_pids=() cpu_at_start=()
    # CPU is counted from here: a replica's start-up (its vocabulary) is not the agents' cost.
    for p in "${replica_pids[@]}"; do cpu_at_start+=("$(cpu_s "$p")"); done
    started=$(date +%s.%N)
    read -r busy_at_start total_at_start < <(machine_cpu)
    for ((m = 0; m < missions; m++)); do
      first=$(( m % R )) list=""
      for ((k = 0; k < R; k++)); do list+="${list:+,}127.0.0.1:${ports[$(( (first + k) % R ))]}"; done
      client=("$bin/cvislam_replay" --recording "$recording" --from-mission "$from_mission" --server "$list"
        --mission "m$m" --rate 1 --seconds "$seconds" --copies "$step_copies" --copy-delay "$copy_delay"
        --flush-timeout 30 --report "$step/m$m.json")
      if [ "$budgets" = 1 ]; then
        cgroup_run clients "${client[@]}" >"$step/m$m.log" 2>&1 &
      else
        "${client[@]}" >"$step/m$m.log" 2>&1 &
      fi
      replay_pids+=("$!"); pids+=("$!")
    done
    replays_ok=1
    for p in "${replay_pids[@]}"; do wait "$p" || replays_ok=0; done
    # The replicas' CPU and the clock are read together, at once: the replicas keep running while the figures
    # below are worked out, and on a short step that time would count against the budget.
    ended=$(date +%s.%N)
    cpu_at_end=()
    for p in "${replica_pids[@]}"; do cpu_at_end+=("$(cpu_s "$p")"); done
    read -r busy_now total_now < <(machine_cpu)
    wall=$(python3 -c "print(round($ended - $started, 2))")
    machine_busy=$(python3 -c "print(round(($busy_now - $busy_at_start) / max(1, $total_now - $total_at_start), 2))")
    for ((r = 0; r < R; r++)); do
      p=${replica_pids[$r]}
      stat=""
      [ "$budgets" = 1 ] && stat=", $(cgroup_stat "r${R}_a${N}_replica$r")"
      cpu=$(python3 -c "print(round(${cpu_at_end[$r]} - ${cpu_at_start[$r]}, 2))")
      echo "{\"cpu_s\": $cpu, \"rss_mb\": $(rss_mb "$p")$stat}" > "$step/replica$r.json"
    done
    # PostgreSQL's CPU for this step: its backends for the step's database (they live as long as the replicas'
    # connections), measured before the replicas end them.
    pg_cpu=0
    for p in $(pgrep -f "postgres: postgres $db "); do pg_cpu=$(python3 -c "print(round($pg_cpu + $(cpu_s "$p"), 2))"); done
    echo "{\"cpu_s\": $pg_cpu}" > "$step/postgres.json"
    for p in "${replica_pids[@]}"; do kill -INT "$p" 2>/dev/null || true; done
    for p in "${replica_pids[@]}"; do wait "$p" 2>/dev/null || true; done
    line=$(python3 "$repo/test/scaleout/capacity_step.py" "$step" "$missions" "$R" "$bound_ms" "$wall" "$replays_ok" \
      "$replica_cpus" "$machine_busy")
    steps+=("$line")
    python3 - "$line" <<'PY'
import json, sys
r = json.loads(sys.argv[1])
f = lambda v, d=0: "-" if v is None else f"{v:.{d}f}"
budget = f"  budget used {f(r['budget_used'], 2)}, throttled {r['throttled_periods']}/{r['periods']} periods" \
    if r["replica_cpu_budget"] else ""
budget += f", machine busy {f(r['machine_busy'], 2)}"
print(f"replicas {r['replicas']}  agents {r['agents']:3d} ({r['missions']} missions)  acked {r['acked']}/{r['batches']}  "
      f"ingest p50 {f(r['ingest_ms_p50_median'])} ms  p99 worst agent {f(r['ingest_ms_p99_worst'])} ms, pooled "
      f"{f(r['ingest_ms_p99_pooled'])} ms (during GBA {f(r['ingest_during_gba_ms_p99_worst'])})  ack p50/p99 "
      f"{f(r['ack_ms_p50'])}/{f(r['ack_ms_p99'])} ms  server CPU {r['server_cpu_s']} s in {r['wall_s']} s{budget}  "
      f"merges {r['merges']} (match->optimised p99 {f(r['match_to_optimised_s_p99'], 1)} s), GBA {r['gba_runs']} "
      f"(largest {r['gba_keyframes_max']} KFs, {f(r['gba_solve_s_max'], 1)} s), RSS {f(r['replica_rss_mb_max'])} MB  "
      f"{'keeps up' if r['keeps_up'] else 'DOES NOT KEEP UP'}")
PY
    keeps=$(python3 -c "import json,sys;print(int(json.loads(sys.argv[1])['keeps_up']))" "$line")
    [ "$keeps" = 1 ] || [ "$keep_going" = 1 ] || break
  done
done
mkdir -p "$(dirname "$out")"
printf '%s\n' "${steps[@]}" > "$work/steps.jsonl"
python3 - "$out" "$recording" "$from_mission" "$seconds" "$bound_ms" "$work/steps.jsonl" "$replica_cpus" \
  "$copies" "$one_mission" <<'PY'
import json, sys, os
out, recording, mission, seconds, bound, steps_file, budget, copies, one_mission = sys.argv[1:10]
steps = [json.loads(line) for line in open(steps_file) if line.strip()]
best = {}
for s in steps:
    if s["keeps_up"]:
        best[s["replicas"]] = max(best.get(s["replicas"], 0), s["agents"])
json.dump({"recording": recording, "mission": mission, "seconds": float(seconds), "bound_ms_p99": float(bound),
           "cores": os.cpu_count(), "replica_cpus": float(budget) or None,
           "copies": "one mission" if one_mission == "1" else int(copies),
           "steps": steps, "agents_kept_up": {str(k): v for k, v in best.items()}}, open(out, "w"), indent=1)
print("agents kept up with: " + ", ".join(f"{r} replica(s): {n}" for r, n in sorted(best.items())) + f"  ({out})")
PY
