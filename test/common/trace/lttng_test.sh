#!/usr/bin/env bash
# With -DCVISLAM_LTTNG=ON: an LTTng session sees the trace points of a program that writes no trace of its own,
# with their names and arguments (lttng_demo records 10 spans "orb" and one instant "keyframe_sent").
# Needs lttng-tools and babeltrace2; starts a session daemon (user space only) when none runs, and stops it after.
#
#   lttng_test.sh LTTNG_DEMO_BINARY
set -euo pipefail
demo=$1
tmp=$(mktemp -d)
started=0
cleanup() {
  lttng destroy cvislam-lttng-test >/dev/null 2>&1 || true
  if [ "$started" = 1 ] && [ -f /var/run/lttng/lttng-sessiond.pid ]; then kill "$(cat /var/run/lttng/lttng-sessiond.pid)" || true; fi
  rm -rf "$tmp"
}
trap cleanup EXIT
if ! pgrep -x lttng-sessiond >/dev/null; then
  lttng-sessiond --no-kernel --daemonize
  started=1
fi
lttng create cvislam-lttng-test --output="$tmp/trace" >/dev/null
lttng enable-event -u 'cvislam:*' >/dev/null
lttng start >/dev/null
"$demo"
lttng stop >/dev/null
lttng destroy cvislam-lttng-test >/dev/null
babeltrace2 "$tmp/trace" >"$tmp/events.txt"
spans=$(grep -c 'cvislam:span' "$tmp/events.txt" || true)
orb=$(grep 'cvislam:span' "$tmp/events.txt" | grep -c 'name = "orb".*keys = "frame"' || true)
sent=$(grep 'cvislam:span' "$tmp/events.txt" |
  grep -c 'name = "keyframe_sent".*duration_ns = -1, keys = "keyframe,batch", _values_length = 2, values = \[ \[0\] = 7, \[1\] = 3 \]' || true)
if [ "$spans" -ne 11 ] || [ "$orb" -ne 10 ] || [ "$sent" -ne 1 ]; then
  echo "lttng_test: $spans events ($orb orb spans, $sent keyframe_sent instants); want 11 (10, 1):" >&2
  head -5 "$tmp/events.txt" >&2
  exit 1
fi
echo "lttng_test: an LTTng session saw the 11 trace points, names and arguments included"
