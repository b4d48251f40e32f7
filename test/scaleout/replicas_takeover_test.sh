#!/usr/bin/env bash
# Scale-out on loopback, every part a real process: PostgreSQL (deploy/local_postgres.sh), three cvislam_server
# replicas sharing it, and four missions of two agents each, streamed by cvislam_replay from a recording of a real
# run (two cvislam_agent processes on the EuRoC V1_01 excerpt at real-time pace, recorded by a server with a SQLite store). Each
# mission's agents first contact a different replica; the owner of one mission is killed with SIGKILL mid-run.
# Checks: every mission completes (every batch acknowledged), the store holds every batch exactly once, the
# killed replica's mission was taken over by another replica, whose map holds every keyframe of each agent once.
# Prints the takeover time (SIGKILL to the new owner's lease, and to the agents' last acknowledgement). Then map
# reuse on replicas: a fourth replica loads the recording's mission under a new name (--load-mission), serves it,
# and hands it over when it leaves.
#
#   test/scaleout/replicas_takeover_test.sh BIN_DIR      (CTest: scaleout_replicas_takeover)
set -euo pipefail
bin=${1:?usage: $0 BIN_DIR}
repo=$(cd "$(dirname "$0")/../.." && pwd)
source "$repo/test/scaleout/lib.sh"
v101_excerpt  # sets seq, or skips
scaleout_work scaleout
fail() { echo "FAILED: $*" >&2; keep=1; exit 1; }
now() { date +%s.%N; }

conninfo=$("$repo/deploy/local_postgres.sh" start "$work/pg")
sql() { psql "$conninfo" -tAq -F ' ' -c "$1"; }

# 1. The recording: two agents flying the excerpt one after the other.
record_agents "$seq" || fail "making the recording"

# 2. Three replicas.
ports=()
for r in 0 1 2; do
  p=$(port); ports+=("$p")
  "$bin/cvislam_server" --listen "127.0.0.1:$p" --postgres "$conninfo" --replica "r$r" --lease-ttl 2 --quiet \
    --no-gba >"$work/replica$r.log" 2>&1 &
  pids+=("$!")
done
for r in 0 1 2; do
  wait_for_line "$work/replica$r.log" "listening on" 10 "replica r$r" "${pids[$((1 + r))]}" ||
    fail "replica $r did not start (see $work/replica$r.log)"
done
list() { local first=$1; echo "127.0.0.1:${ports[$first]},127.0.0.1:${ports[$(( (first + 1) % 3 ))]},127.0.0.1:${ports[$(( (first + 2) % 3 ))]}"; }

# 3. Four missions of two agents, at half real time (the excerpt is 4.7 s), each starting at another replica.
replays=()
for m in 0 1 2 3; do
  "$bin/cvislam_replay" --recording "$work/recording.db" --server "$(list $((m % 3)))" --mission "m$m" --rate 0.5 \
    --flush-timeout 40 --report "$work/m$m.json" >"$work/m$m.log" 2>&1 &
  replays+=("$!")
  pids+=("$!")
done
# shellcheck disable=SC2317  # called through wait_until
leased() { [ "$(sql "SELECT count(*) FROM cvislam_leases")" = "$1" ]; }
wait_until 10 "a lease for each of the four missions" leased 4 || true  # the lookup of m1's owner below says more
sleep 2
read -r victim_address old_epoch < <(sql "SELECT address, epoch FROM cvislam_leases WHERE mission = 'm1'")
victim=-1
for r in 0 1 2; do [ "127.0.0.1:${ports[$r]}" = "$victim_address" ] && victim=$r; done
[ "$victim" -ge 0 ] || fail "no replica serves m1 ($victim_address)"
before=$(sql "SELECT count(*) FROM cvislam_records WHERE mission = 'm1' AND kind = 2")
kill -9 "${pids[$((1 + victim))]}"
killed=$(now)
wait "${pids[$((1 + victim))]}" 2>/dev/null || true  # reaped here, so bash does not report "Killed"
echo "SIGKILL to replica r$victim, owner of m1 ($before batches stored); missions it served: $(sql "SELECT string_agg(mission, ',') FROM cvislam_leases WHERE address = '$victim_address'")"
# shellcheck disable=SC2317  # called through wait_until; leaves the lease's row in `row`
lease_moved() { row=$(sql "SELECT address, epoch FROM cvislam_leases WHERE mission = 'm1'"); [ "${row#* }" != "$old_epoch" ]; }
wait_until 15 "another replica to take m1's lease over" lease_moved || fail "nobody took m1 over within 15 s"
taken=$(now)
new_address=${row% *}
rc=0
for i in "${!replays[@]}"; do wait "${replays[$i]}" || { echo "mission m$i did not complete (see $work/m$i.log)"; rc=1; }; done
done_at=$(now)
[ "$rc" = 0 ] || fail "not every mission completed"

# 4. Exactly once, in the store and in the new owner's map.
# The recorded agents' batch counts (a real-time recording: the two agents may differ by one).
declare -A expected
while read -r agent batches; do expected[$agent]=$batches; done < <(python3 -c "
import json
for a in json.load(open('$work/m0.json'))['agents']: print(a['agent'], a['batches'])")
total_expected=$(( 4 * (expected[0] + expected[1]) ))
while read -r mission agent n distinct top; do
  e=${expected[$agent]:-?}
  [ "$n" = "$e" ] && [ "$distinct" = "$e" ] && [ "$top" = "$e" ] ||
    fail "mission $mission agent $agent: $n batches stored ($distinct distinct, newest $top), expected $e once each"
done < <(sql "SELECT mission, agent, count(*), count(DISTINCT sequence), max(sequence) FROM cvislam_records WHERE kind = 2 GROUP BY 1, 2 ORDER BY 1, 2")
[ "$(sql "SELECT count(*) FROM cvislam_records WHERE kind = 2")" = "$total_expected" ] ||
  fail "the store does not hold the $total_expected batches recorded"
[ "$new_address" != "$victim_address" ] || fail "m1 is still leased to the killed replica"
for a in 0 1; do
  "$bin/cvislam_mapctl" --server "$new_address" trajectory m1 "$a" --out "$work/m1_agent$a.txt" >/dev/null ||
    fail "reading m1's trajectory of agent $a from its new owner $new_address"
  n=$(grep -vc '^#' "$work/m1_agent$a.txt")
  unique=$(grep -v '^#' "$work/m1_agent$a.txt" | awk '{print $1}' | sort -u | wc -l)
  [ "$n" -gt 0 ] && [ "$n" = "$unique" ] || fail "m1 agent $a on its new owner: $n keyframes, $unique distinct times"
  recorded_kf=$(grep -vc '^#' "$work/agent$a/keyframes.txt" 2>/dev/null || true)
  [ "${recorded_kf:-0}" = 0 ] || [ "$n" -le "$recorded_kf" ] ||
    fail "m1 agent $a: $n keyframes, more than the $recorded_kf the agent made"
  echo "m1 agent $a: $n keyframes on the new owner, each once"
done

# 5. Map-service reads at a replica that does not serve the mission are passed to its owner: the same answers.
other=""
for r in 0 1 2; do
  address="127.0.0.1:${ports[$r]}"
  [ "$r" != "$victim" ] && [ "$address" != "$new_address" ] && other=$address
done
[ -n "$other" ] || fail "no live replica besides m1's new owner"
for a in 0 1; do
  "$bin/cvislam_mapctl" --server "$other" trajectory m1 "$a" --out "$work/m1_agent${a}_via.txt" >/dev/null ||
    fail "reading m1's trajectory of agent $a through $other, which does not serve it"
  cmp -s "$work/m1_agent$a.txt" "$work/m1_agent${a}_via.txt" ||
    fail "m1's trajectory of agent $a differs when read through $other"
done
"$bin/cvislam_mapctl" --server "$new_address" export m1 --out "$work/export_owner" >/dev/null ||
  fail "exporting m1 from its owner"
"$bin/cvislam_mapctl" --server "$other" export m1 --out "$work/export_via" >/dev/null ||
  fail "exporting m1 through $other (a stream relayed from the owner)"
diff -rq "$work/export_owner" "$work/export_via" >/dev/null || fail "m1's export differs when read through $other"
for address in "$other" "$new_address"; do
  listed=$("$bin/cvislam_mapctl" --server "$address" --json list |
    python3 -c "import json,sys;print(','.join(m['name'] for m in json.load(sys.stdin).get('missions',[])))")
  [ "$listed" = "m0,m1,m2,m3" ] || fail "the missions listed by $address: '$listed', expected m0,m1,m2,m3"
done
"$bin/cvislam_mapctl" --server "$other" maps nosuchmission >/dev/null 2>&1 && fail "a mission nobody serves was listed"
echo "reads through $other (not m1's owner): trajectories and export identical to the owner's; list shows 4 missions"

# 6. Map reuse on a replica: a fourth replica loads the recording's mission as "reused" into the shared store and
# serves it, read through another replica as at its owner. When
# it leaves cleanly a live replica takes "reused" over and serves the same map; the same command line again finds
# the copy held and copies nothing.
keyframes_of() {  # keyframes_of ADDRESS MISSION AGENT
  "$bin/cvislam_mapctl" --server "$1" trajectory "$2" "$3" --out "$work/kf.txt" >/dev/null || return 1
  grep -vc '^#' "$work/kf.txt"
}
start_loader() {  # start_loader LOG: sets loader, loader_port
  loader_port=$(port)
  "$bin/cvislam_server" --listen "127.0.0.1:$loader_port" --postgres "$conninfo" --replica r3 --lease-ttl 2 --quiet \
    --no-gba --load-mission recorded=reused --load-from "$work/recording.db" >"$1" 2>&1 &
  loader=$!
  pids+=("$loader")
  wait_for_line "$1" "listening on" 30 "replica r3 loading a mission" "$loader" ||
    fail "replica r3 with --load-mission did not start (see $1)"
}
start_loader "$work/loader.log"
grep -q "loaded mission 'recorded' of .* as 'reused'" "$work/loader.log" || fail "r3 did not say what it loaded (see $work/loader.log)"
[ "$(sql "SELECT address FROM cvislam_leases WHERE mission = 'reused'")" = "127.0.0.1:$loader_port" ] ||
  fail "the loading replica r3 does not hold the lease of 'reused'"
# The server's redundancy removal depends on timing, so the loaded map is compared with itself read at its owner,
# and with what the agents made, not with m0's.
check_reused() {  # check_reused OWNER: each agent's keyframes read through $other are the owner's, once each
  local a n made
  for a in 0 1; do
    keyframes_of "$1" reused "$a" >/dev/null || fail "reading the loaded mission 'reused' at its owner $1"
    cp "$work/kf.txt" "$work/reused_owner.txt"
    n=$(keyframes_of "$other" reused "$a") || fail "reading the loaded mission 'reused' through $other"
    cmp -s "$work/kf.txt" "$work/reused_owner.txt" || fail "'reused' agent $a differs read through $other"
    made=$(grep -vc '^#' "$work/agent$a/keyframes.txt")
    [ "$n" -gt 0 ] && [ "$n" -le "$made" ] || fail "'reused' agent $a: $n keyframes (the agent made $made)"
    [ "$(grep -v '^#' "$work/kf.txt" | awk '{print $1}' | sort -u | wc -l)" = "$n" ] || fail "'reused' agent $a: a keyframe twice"
  done
}
check_reused "127.0.0.1:$loader_port"
kill -INT "$loader"; wait "$loader" || fail "replica r3's clean shutdown (see $work/loader.log)"
# shellcheck disable=SC2317  # called through wait_until
reused_moved() { local a; a=$(sql "SELECT address FROM cvislam_leases WHERE mission = 'reused' AND expires_at > now()"); [ -n "$a" ] && [ "$a" != "127.0.0.1:$loader_port" ]; }
wait_until 10 "a live replica to take 'reused' over" reused_moved || fail "nobody took 'reused' over after r3 left"
check_reused "$(sql "SELECT address FROM cvislam_leases WHERE mission = 'reused'")"
stored=$(sql "SELECT count(*) FROM cvislam_records WHERE mission = 'reused'")
start_loader "$work/loader2.log"
grep -q "mission 'reused' is held already" "$work/loader2.log" || fail "r3 restarted copied again (see $work/loader2.log)"
[ "$(sql "SELECT count(*) FROM cvislam_records WHERE mission = 'reused'")" = "$stored" ] ||
  fail "the second --load-mission changed the stored copy ($stored records before)"
echo "map reuse on replicas: r3 loaded 'reused' ($stored records) and served it; after r3 left, another replica did;" \
  "started again, r3 copied nothing"
python3 - "$work" "$killed" "$taken" "$done_at" <<'PY'
import json, sys
work, killed, taken, done_at = sys.argv[1], *map(float, sys.argv[2:])
for m in range(4):
    j = json.load(open(f"{work}/m{m}.json"))
    for a in j["agents"]:
        print(f"m{m} agent {a['agent']}: {a['acked']}/{a['batches']} acknowledged, {a['streams']} streams, "
              f"{a['redirects']} redirects, longest gap {a['longest_gap_s']:.2f} s, "
              f"ack p50 {a.get('ack_ms_p50', 0):.0f} ms")
print(f"takeover: the new owner held m1's lease {taken - killed:.2f} s after the SIGKILL (lease TTL 2 s)")
gaps = [a["longest_gap_s"] for a in json.load(open(f"{work}/m1.json"))["agents"]]
print(f"m1's agents were without a stream for at most {max(gaps):.2f} s")
PY
echo "PASSED: 4 missions x 2 agents over 3 replicas, owner of m1 killed, every batch stored once ($total_expected)"
