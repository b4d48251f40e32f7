#!/usr/bin/env bash
# How a dead replica's missions move: PostgreSQL, three cvislam_server replicas, and M one-agent missions streamed
# by cvislam_replay from a recording (the first recorded agent of each), a third of them first contacting each
# replica. Once every mission is leased, the replica serving the most missions is SIGKILLed. The script follows the
# leases table every 50 ms and prints, per surviving replica, how many of the dead replica's missions it took, and
# the time from the SIGKILL to each mission's new lease (p50 and max); then, once the replays end, every agent's
# longest time without a stream. With --replica-cpus C each replica runs in a cgroup of C cores (lib.sh).
#
#   test/scaleout/takeover_spread.sh BIN_DIR RECORDING [--from-mission M] [--missions 24] [--seconds 40]
#       [--kill-after 15] [--lease-ttl 3] [--replica-cpus C] [--out FILE.json]
set -euo pipefail
usage() { sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
[ $# -ge 2 ] || usage
bin=$1 recording=$2
shift 2
repo=$(cd "$(dirname "$0")/../.." && pwd)
from_mission="" missions=24 seconds=40 kill_after=15 ttl=3 replica_cpus=0
out="$repo/out/bench/takeover_spread.json"
while [ $# -gt 0 ]; do
  case "$1" in
    --from-mission) from_mission=$2; shift 2 ;;
    --missions) missions=$2; shift 2 ;;
    --seconds) seconds=$2; shift 2 ;;
    --kill-after) kill_after=$2; shift 2 ;;
    --lease-ttl) ttl=$2; shift 2 ;;
    --replica-cpus) replica_cpus=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    -h|--help) usage ;;
    *) echo "takeover_spread: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
[ -f "$recording" ] || { echo "takeover_spread: no recording '$recording'" >&2; exit 2; }
source "$repo/test/scaleout/lib.sh"
scaleout_work takeover-spread
budgets=$(python3 -c "print(int(float('$replica_cpus') > 0))")
[ "$budgets" = 0 ] || cgroup_init "cvislam-takeover-$$" || exit 2
conninfo=$("$repo/deploy/local_postgres.sh" start "$work/pg")
sql() { psql "$conninfo" -tAq -F ' ' -c "$1"; }
mission_arg=()
[ -n "$from_mission" ] && mission_arg=(--from-mission "$from_mission")

ports=() replica_pids=()
for r in 0 1 2; do
  p=$(port); ports+=("$p")
  cmd=("$bin/cvislam_server" --listen "127.0.0.1:$p" --postgres "$conninfo" --replica "r$r" --lease-ttl "$ttl"
    --quiet --output "$work/out$r")
  run_budgeted "replica$r" "$replica_cpus" "$work/replica$r.log" "${cmd[@]}"
  replica_pids+=("$started_pid"); pids+=("$started_pid")
done
for r in 0 1 2; do
  wait_for_line "$work/replica$r.log" "listening on" 20 "replica r$r" "${replica_pids[$r]}" || exit 1
done
replays=()
for ((m = 0; m < missions; m++)); do
  first=$((m % 3))
  list="127.0.0.1:${ports[$first]},127.0.0.1:${ports[$(((first + 1) % 3))]},127.0.0.1:${ports[$(((first + 2) % 3))]}"
  "$bin/cvislam_replay" --recording "$recording" "${mission_arg[@]}" --agents 0 --server "$list" --mission "m$m" \
    --rate 1 --seconds "$seconds" --flush-timeout 60 --report "$work/m$m.json" >"$work/m$m.log" 2>&1 &
  replays+=("$!"); pids+=("$!")
done
sleep "$kill_after"
[ "$(sql "SELECT count(*) FROM cvislam_leases WHERE expires_at > now()")" = "$missions" ] ||
  { echo "takeover_spread: not every mission was leased after $kill_after s" >&2; keep=1; exit 1; }
read -r victim_address victim_missions < <(sql "SELECT address, count(*) FROM cvislam_leases GROUP BY address ORDER BY 2 DESC, 1 LIMIT 1")
victim=-1
for r in 0 1 2; do [ "127.0.0.1:${ports[$r]}" = "$victim_address" ] && victim=$r; done
sql "SELECT mission FROM cvislam_leases WHERE address = '$victim_address' ORDER BY 1" > "$work/victim_missions.txt"
kill -9 "${replica_pids[$victim]}"
killed=$(date +%s.%N)
wait "${replica_pids[$victim]}" 2>/dev/null || true
echo "SIGKILL to replica r$victim, which served $victim_missions of $missions missions"
# The leases every 50 ms until none of the dead replica's missions is left with it (or 30 s).
python3 - "$conninfo" "$victim_address" "$killed" "$work/victim_missions.txt" "$work/moves.json" <<'PY'
import json, subprocess, sys, time
conninfo, dead, killed, listed, out = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4], sys.argv[5]
missions = [m.strip() for m in open(listed) if m.strip()]
moved = {}
while len(moved) < len(missions) and time.time() - killed < 30:
    rows = subprocess.run(["psql", conninfo, "-tAq", "-F", " ", "-c",
                           "SELECT mission, address FROM cvislam_leases WHERE expires_at > now()"],
                          capture_output=True, text=True).stdout.split("\n")
    now = time.time()
    for row in rows:
        if not row.strip():
            continue
        mission, address = row.split(" ")
        if mission in missions and mission not in moved and address != dead:
            moved[mission] = {"to": address, "after_s": round(now - killed, 3)}
    time.sleep(0.05)
json.dump({"missions": missions, "moved": moved}, open(out, "w"))
PY
rc=0
for p in "${replays[@]}"; do wait "$p" || rc=1; done
for r in 0 1 2; do [ "$r" = "$victim" ] || kill -INT "${replica_pids[$r]}" 2>/dev/null || true; done
for r in 0 1 2; do [ "$r" = "$victim" ] || wait "${replica_pids[$r]}" 2>/dev/null || true; done
mkdir -p "$(dirname "$out")"
python3 - "$work" "$missions" "$victim_address" "$out" "$rc" "$replica_cpus" "$ttl" <<'PY'
import json, sys
work, missions, dead, out, rc, budget, ttl = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5], float(sys.argv[6]), float(sys.argv[7])
moves = json.load(open(f"{work}/moves.json"))
per = {}
for m in moves["moved"].values():
    per[m["to"]] = per.get(m["to"], 0) + 1
times = sorted(m["after_s"] for m in moves["moved"].values())
gaps, acked, batches = [], 0, 0
for m in range(missions):
    for a in json.load(open(f"{work}/m{m}.json"))["agents"]:
        acked += a["acked"]; batches += a["batches"]
        if f"m{m}" in moves["missions"]:
            gaps.append(a["longest_gap_s"])
result = {"missions": missions, "dead_replica_missions": len(moves["missions"]), "taken": len(moves["moved"]),
          "taken_by": per, "takeover_s_p50": times[len(times) // 2] if times else None,
          "takeover_s_max": times[-1] if times else None, "lease_ttl_s": ttl, "replica_cpus": budget or None,
          "dead_missions_longest_gap_s_max": max(gaps, default=None), "acked": acked, "batches": batches,
          "replays_finished": rc == "0"}
json.dump(result, open(out, "w"), indent=1)
print(f"the dead replica's {len(moves['missions'])} missions: {len(moves['moved'])} taken over, by "
      + ", ".join(f"{a}: {n}" for a, n in sorted(per.items()))
      + f"; SIGKILL -> new lease p50 {result['takeover_s_p50']} s, max {result['takeover_s_max']} s (TTL {ttl:g} s); "
      f"their agents' longest gap {result['dead_missions_longest_gap_s_max']} s; {acked}/{batches} batches acknowledged ({out})")
PY
