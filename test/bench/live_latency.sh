#!/usr/bin/env bash
# Latency of the agent's live state on a driver's topics: from a frame's capture to its state on the state topic
# (frame_to_state) and from an IMU sample's capture to its propagated state (imu_to_propagated_state), p50/p90/p99/max.
# Starts iox-roudi (deploy/roudi_config.toml), writes the sequence's rig as Kalibr files, and runs cvislam_agent --live
# pinned to AGENT_CPUS (default "1": the whole agent on one core) and cvislam_sensor_publisher at sensor pace pinned
# to OTHER_CPUS (default "0", with RouDi).
#
#   test/bench/live_latency.sh [BUILD_DIR] SEQ_DIR [mono|stereo] [AGENT_CPUS] [OTHER_CPUS]
#
# Prints one markdown row; the agent's outputs and logs go to $RESULTS (default /tmp/cvislam-live-latency).
# Needs no iox-roudi running (iceoryx allows one per machine).
set -euo pipefail
cd "$(dirname "$0")/../.."
build=${1:-build/default}
sequence=${2:?usage: live_latency.sh [BUILD_DIR] SEQ_DIR [mono|stereo] [AGENT_CPUS] [OTHER_CPUS]}
mode=${3:-stereo}
agent_cpus=${4:-1}
other_cpus=${5:-0}
results=${RESULTS:-/tmp/cvislam-live-latency}/$(basename "$sequence")-$mode
for tool in cvislam_agent cvislam_sensor_publisher; do
  [[ -x $build/bin/$tool ]] || { echo "missing $build/bin/$tool: build it first" >&2; exit 1; }
done
if pgrep -x iox-roudi > /dev/null; then
  echo "an iox-roudi is running already; stop it first (one per machine)" >&2
  exit 1
fi
rm -rf "$results"
mkdir -p "$results"
"$build/bin/cvislam_sensor_publisher" --dataset "$sequence" --mode "$mode" --write-calibration "$results/kalibr" \
  2> "$results/calibration.log"

taskset -c "$other_cpus" iox-roudi -m off -c deploy/roudi_config.toml > "$results/roudi.log" 2>&1 &
roudi=$!
trap 'kill $roudi 2>/dev/null || true' EXIT
for _ in $(seq 100); do grep -q "RouDi is ready" "$results/roudi.log" && break; sleep 0.1; done

stream=latency$$
taskset -c "$agent_cpus" "$build/bin/cvislam_agent" --live "$stream" --mode "$mode" --output "$results/agent" \
  --calibration "$results/kalibr/camchain-imucam.yaml" --imu-calibration "$results/kalibr/imu.yaml" \
  > "$results/agent.log" 2>&1 &
agent=$!
taskset -c "$other_cpus" "$build/bin/cvislam_sensor_publisher" --dataset "$sequence" --mode "$mode" --name "$stream" \
  --quiet > "$results/publisher.log" 2>&1
wait $agent || { echo "the agent failed (exit $?): see $results/agent.log" >&2; exit 1; }

stage() {
  jq -r --arg s "$1" '.[$s] | "\(.p50_ms * 1000 | round / 1000) / \(.p99_ms * 1000 | round / 1000) / \(.max_ms * 1000 | round / 1000) (\(.count))"' \
    "$results/agent/latency.json"
}
echo "| $(basename "$sequence") | $mode | $agent_cpus | $(stage tracking_total) | $(stage frame_to_state) | $(stage imu_to_propagated_state) | $(jq -c .live "$results/agent/summary.json") |"
