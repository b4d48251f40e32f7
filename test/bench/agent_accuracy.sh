#!/usr/bin/env bash
# Accuracy of cvislam_agent on the simulator's presets: renders each preset once (fixed seed, stereo) into a
# cache folder, runs every agent of it alone in mono-inertial and stereo-inertial mode (--pace sync, so the
# figures are reproducible), and scores the per-frame trajectory with cvislam_eval (SE3 ATE, Sim3 scale).
#
#   [MODES="mono stereo"] [CONFIG=agent.yaml] test/bench/agent_accuracy.sh [BUILD_DIR] [PRESET...]
#                                                  (default: build/default, loop aggressive euroc-mh)
#
# Writes a markdown table to stdout and everything else to $RESULTS (default $CACHE/results, with
# CACHE=${CVISLAM_SIM_CACHE:-/tmp/cvislam-sim}). CONFIG is passed to every agent as --config.
set -euo pipefail
cd "$(dirname "$0")/../.."
build=${1:-build/default}
shift || true
presets=("$@")
[[ ${#presets[@]} -gt 0 ]] || presets=(loop aggressive euroc-mh)
cache=${CVISLAM_SIM_CACHE:-/tmp/cvislam-sim}
results=${RESULTS:-$cache/results}
config_args=()
[[ -z ${CONFIG:-} ]] || config_args=(--config "$CONFIG")
mkdir -p "$results"
for tool in cvislam_sim cvislam_agent cvislam_eval; do
  [[ -x $build/bin/$tool ]] || { echo "missing $build/bin/$tool: build it first (cmake --build $build)" >&2; exit 1; }
done

echo "| preset | agent | mode | frames tracked | keyframes | IMU init [s] | ATE SE3 [m] | scale error [%] | path [m] |"
echo "|---|---|---|---|---|---|---|---|---|"
for preset in "${presets[@]}"; do
  if [[ ! -f $cache/$preset/mission.yaml ]]; then
    echo "rendering $preset (once) ..." >&2
    "$build/bin/cvislam_sim" --preset "$preset" --out "$cache/$preset" --seed 1 --stereo --overwrite >&2
  fi
  for agent_dir in "$cache/$preset"/agent*; do
    agent=$(basename "$agent_dir")
    for mode in ${MODES:-mono stereo}; do
      out=$results/$preset-$agent-$mode
      if ! "$build/bin/cvislam_agent" --dataset "$agent_dir" --output "$out" --mode "$mode" --pace sync --quiet "${config_args[@]}" \
          > "$out.log" 2>&1; then
        echo "| $preset | $agent | $mode | agent failed: see $out.log | | | | | |"
        continue
      fi
      "$build/bin/cvislam_eval" --estimate "$out/trajectory.txt" --groundtruth "$agent_dir" --json "$out/eval.json" \
        > "$out/eval.txt" 2>&1 || true
      jq -r --arg p "$preset" --arg a "$agent" --arg m "$mode" --slurpfile e "$out/eval.json" \
        '"| \($p) | \($a) | \($m) | \(.tracked_frames)/\(.frames) | \(.keyframes) | \(.imu_initialised_at_s * 100 | round / 100) | " +
         (($e[0].se3.rmse * 1000 | round / 1000) | tostring) + " | " +
         (($e[0].scale_error_percent // 0) * 100 | round / 100 | tostring) + " | " + ($e[0].groundtruth_path_m | round | tostring) + " |"' \
        "$out/summary.json" 2>/dev/null || echo "| $preset | $agent | $mode | evaluation failed: see $out/eval.txt | | | | | |"
    done
  done
done
