# shellcheck shell=bash
# Waiting for something a script started, in one place (sourced by deploy/run_mission.sh and, through
# test/scaleout/lib.sh, the scale-out scripts). Each function polls every 0.05 s until its condition holds and
# returns 0; after TIMEOUT_S seconds (a whole number), or as soon as the process PID it was given has exited, it
# says on stderr what did not come up, with the end of the process's log, and returns 1. The caller decides
# whether that ends the script (`|| exit 1`) or not (`|| true`). Needs bash 5 (EPOCHREALTIME).
#
#   wait_for_line FILE PATTERN TIMEOUT_S WHAT [PID]    FILE has a line matching PATTERN (grep's basic regex)
#   wait_for_file FILE TIMEOUT_S WHAT [PID [LOG]]      FILE exists and is not empty
#   wait_until TIMEOUT_S WHAT COMMAND [ARG...]         COMMAND succeeds; it runs in the calling shell, so it may
#                                                      set variables the caller reads afterwards

# _wait_poll TIMEOUT_S PID COMMAND...: 0 once COMMAND succeeds, 1 after TIMEOUT_S, 2 when PID exited first.
_wait_poll() {
  local timeout_s=$1 pid=$2 now deadline
  shift 2
  now=${EPOCHREALTIME/[!0-9]/}  # microseconds; the separator follows the locale
  deadline=$((now + timeout_s * 1000000))
  while true; do
    "$@" && return 0
    if [ -n "$pid" ] && ! kill -0 "$pid" 2>/dev/null; then
      "$@" && return 0  # it may have written what was awaited just before it exited
      return 2
    fi
    now=${EPOCHREALTIME/[!0-9]/}
    [ "$now" -lt "$deadline" ] || return 1
    sleep 0.05
  done
}

# _wait_failed STATUS TIMEOUT_S WHAT PID LOG: the message for _wait_poll's STATUS, then the end of LOG.
_wait_failed() {
  local status=$1 timeout_s=$2 what=$3 pid=$4 log=$5 me=${0##*/}
  me=${me%.sh}
  if [ "$status" = 2 ]; then
    echo "$me: the process (pid $pid) exited while waiting for $what" >&2
  else
    echo "$me: gave up after $timeout_s s waiting for $what" >&2
  fi
  if [ -n "$log" ] && [ -s "$log" ]; then
    echo "  the end of $log:" >&2
    tail -n 20 "$log" | sed 's/^/    /' >&2
  fi
  return 1
}

wait_for_line() {
  local file=$1 pattern=$2 timeout_s=$3 what=$4 pid=${5:-} status=0
  _wait_poll "$timeout_s" "$pid" grep -q -- "$pattern" "$file" 2>/dev/null || status=$?
  [ "$status" = 0 ] || _wait_failed "$status" "$timeout_s" "$what (\"$pattern\" in $file)" "$pid" "$file"
}

wait_for_file() {
  local file=$1 timeout_s=$2 what=$3 pid=${4:-} log=${5:-} status=0
  _wait_poll "$timeout_s" "$pid" test -s "$file" || status=$?
  [ "$status" = 0 ] || _wait_failed "$status" "$timeout_s" "$what ($file)" "$pid" "$log"
}

wait_until() {
  local timeout_s=$1 what=$2 status=0
  shift 2
  _wait_poll "$timeout_s" "" "$@" || status=$?
  [ "$status" = 0 ] || _wait_failed "$status" "$timeout_s" "$what" "" ""
}
