# shellcheck shell=bash
# Shared by the scale-out scripts (sourced, with `repo` set): a work folder that the postgres user can enter, the
# processes started into `pids`, and a cleanup at exit that kills them, stops the database under "$work/pg" and
# removes the folder (unless `keep` is 1: then it says where the logs are); and deploy/lib/wait.sh's waits.
source "$repo/deploy/lib/wait.sh"
scaleout_work() {  # scaleout_work NAME: sets `work`, `pids` and the exit trap
  work=$(mktemp -d "/tmp/cvislam-$1.XXXXXX")
  chmod 755 "$work"  # the postgres user runs the database under it
  pids=()
  trap scaleout_cleanup EXIT
}
scaleout_cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null || true; wait "$p" 2>/dev/null || true; done
  "$repo/deploy/local_postgres.sh" stop "$work/pg" >/dev/null 2>&1 || true
  cgroup_cleanup
  if [ "${keep:-0}" = 0 ]; then rm -rf "$work"; else echo "logs kept in $work"; fi
}
v101_excerpt() {  # sets `seq` to the real EuRoC V1_01 excerpt, or exits 77 (CTest: skipped) saying where it looked
  seq="${CVISLAM_DATA_DIR:-$repo/../shared/data}/euroc-v101-excerpt"
  if [ ! -d "$seq/mav0" ]; then echo "SKIPPED: no $seq (set CVISLAM_DATA_DIR)"; exit 77; fi
}
# record_agents SEQUENCE: $work/recording.db, a server's SQLite store of mission "recorded", in which two
# cvislam_agent processes (ids 0 and 1, with `bin` set) flew SEQUENCE one after the other at real-time pace; the
# agents' outputs in $work/agent0 and agent1. Says what failed and where its log is.
record_agents() {
  local rec_port recorder a
  rec_port=$(port)
  "$bin/cvislam_server" --listen "127.0.0.1:$rec_port" --store "$work/recording.db" --quiet --no-gba \
    >"$work/recorder.log" 2>&1 &
  recorder=$!
  pids+=("$recorder")
  # Generous: the scale-out tests also run under ThreadSanitizer (test/run_sanitizers.sh), which starts slowly.
  wait_for_line "$work/recorder.log" "listening on" 30 "the recording server" "$recorder" ||
    { echo "the recording server did not start (see $work/recorder.log)" >&2; return 1; }
  for a in 0 1; do
    "$bin/cvislam_agent" --dataset "$1" --output "$work/agent$a" --pace realtime --quiet \
      --server "127.0.0.1:$rec_port" --mission recorded --agent-id "$a" >"$work/agent$a.log" 2>&1 ||
      { echo "recording agent $a failed (see $work/agent$a.log)" >&2; return 1; }
  done
  kill -INT "$recorder"
  wait "$recorder" || { echo "the recording server failed (see $work/recorder.log)" >&2; return 1; }
}
port() { python3 -c 'import socket;s=socket.socket();s.bind(("127.0.0.1",0));print(s.getsockname()[1])'; }

# CPU budgets: each replica (and PostgreSQL, and the replay clients) in a cgroup of its own with a CPU quota, so
# that on one machine "a replica" means "a machine of N cores". cgroup v1's cpu controller (Debian 12 with the
# legacy hierarchy, as on the team's VMs) or v2's cpu.max; needs root. The quota is spread over periods of
# cgroup_period_us: a short period keeps a budgeted process from waiting long for its next slice, as it would not
# on a slower machine of its own.
cgroup_period_us=${cgroup_period_us:-20000}
cgroup_dir=""
cgroup_v=""
cgroup_init() {  # cgroup_init NAME: a parent group for this run; says what to fix and fails when none can be made
  if [ -f /sys/fs/cgroup/cpu/cpu.cfs_quota_us ]; then
    cgroup_v=1 cgroup_dir=/sys/fs/cgroup/cpu/$1
  elif [ -f /sys/fs/cgroup/cgroup.controllers ] && grep -qw cpu /sys/fs/cgroup/cgroup.controllers; then
    cgroup_v=2 cgroup_dir=/sys/fs/cgroup/$1
    echo +cpu > /sys/fs/cgroup/cgroup.subtree_control 2>/dev/null || true
  else
    echo "no cgroup cpu controller (neither /sys/fs/cgroup/cpu nor cpu in /sys/fs/cgroup/cgroup.controllers):" \
      "CPU budgets need one" >&2
    return 1
  fi
  mkdir -p "$cgroup_dir" 2>/dev/null || { echo "cannot make $cgroup_dir: CPU budgets need root" >&2; return 1; }
  [ "$cgroup_v" = 1 ] || echo +cpu > "$cgroup_dir/cgroup.subtree_control"
}
cgroup_make() {  # cgroup_make SUB CPUS: a group with a budget of CPUS cores (0: no limit)
  local g="$cgroup_dir/$1" quota=-1
  mkdir -p "$g"
  if [ "$(python3 -c "print(int(float('$2') > 0))")" = 1 ]; then
    quota=$(python3 -c "print(max(1000, round(float('$2') * $cgroup_period_us)))")
  fi
  if [ "$cgroup_v" = 1 ]; then
    echo "$cgroup_period_us" > "$g/cpu.cfs_period_us"
    echo "$quota" > "$g/cpu.cfs_quota_us"
  else
    [ "$quota" = -1 ] && quota=max
    echo "$quota $cgroup_period_us" > "$g/cpu.max"
  fi
}
cgroup_run() {  # cgroup_run SUB COMMAND...: runs COMMAND in the group (in the background: add &)
  local g="$cgroup_dir/$1"
  shift
  echo "$BASHPID" > "$g/cgroup.procs"
  exec "$@"
}
run_budgeted() {  # run_budgeted GROUP CPUS LOG COMMAND...: COMMAND in the background, in a new group of CPUS cores
  # when `budgets` is 1 (else as it is), its output to LOG; sets `started_pid`
  local group=$1 cpus=$2 log=$3
  shift 3
  if [ "${budgets:-0}" = 1 ]; then
    cgroup_make "$group" "$cpus"
    cgroup_run "$group" "$@" >"$log" 2>&1 &
  else
    "$@" >"$log" 2>&1 &
  fi
  started_pid=$!
}
cgroup_move() {  # cgroup_move SUB PID...: moves running processes into the group
  local g="$cgroup_dir/$1" p
  shift
  for p in "$@"; do echo "$p" > "$g/cgroup.procs"; done
}
cgroup_stat() {  # cgroup_stat SUB: the group's throttling as JSON fields: nr_periods, nr_throttled, throttled_s
  python3 - "$cgroup_dir/$1/cpu.stat" "$cgroup_v" <<'PY'
import sys
stat = dict(line.split() for line in open(sys.argv[1]) if line.strip())
scale = 1e-9 if sys.argv[2] == "1" else 1e-6  # v1: throttled_time [ns]; v2: throttled_usec
throttled = stat.get("throttled_time", stat.get("throttled_usec", 0))
print(f'"nr_periods": {int(stat.get("nr_periods", 0))}, "nr_throttled": {int(stat.get("nr_throttled", 0))}, '
      f'"throttled_s": {int(throttled) * scale:.3f}')
PY
}
cgroup_cleanup() {  # removes the groups once their processes have ended
  [ -n "$cgroup_dir" ] && [ -d "$cgroup_dir" ] || return 0
  local g
  for g in "$cgroup_dir"/*/; do [ -d "$g" ] && rmdir "$g" 2>/dev/null; done
  rmdir "$cgroup_dir" 2>/dev/null || true
}
