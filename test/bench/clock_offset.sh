#!/usr/bin/env bash
# What a camera-IMU clock offset costs the agent: renders PRESET (seed 1, stereo, agent0 scored) with the cameras'
# clock shifted by each OFFSET against the IMU (cvislam_sim --camera-clock-shift), then runs the agent at
# --pace sync, mono and stereo, three times per offset: with the offset unknown and held (the images' stamps taken as
# they are), given as Kalibr's timeshift_cam_imu, and unknown but estimated (--time-offset estimate, from 0). Scores the
# per-frame trajectory (SE3 ATE) against ground truth, and says where the estimate was 10 s into the run and at its end.
#
#   [DURATION=30] [OFFSETS="0 -20 10 30"] test/bench/clock_offset.sh [BUILD_DIR] [PRESET...]   (default: loop euroc-mh)
#
# Prints a markdown table; renders go to $CACHE (default /tmp/cvislam-clock), runs to $CACHE/results.
set -euo pipefail
cd "$(dirname "$0")/../.."
build=${1:-build/default}
shift || true
presets=("$@")
[[ ${#presets[@]} -gt 0 ]] || presets=(loop euroc-mh)
cache=${CACHE:-/tmp/cvislam-clock}
duration=${DURATION:-30}
offsets=${OFFSETS:-0 -20 10 30}
mkdir -p "$cache/results"
for tool in cvislam_sim cvislam_agent cvislam_eval cvislam_sensor_publisher; do
  [[ -x $build/bin/$tool ]] || { echo "missing $build/bin/$tool: build it first" >&2; exit 1; }
done

ate() {  # trajectory, sequence
  "$build/bin/cvislam_eval" --estimate "$1" --groundtruth "$2" --json "$1.eval.json" -q > /dev/null 2>&1 &&
    jq -r '(.se3.rmse * 10000 | round / 100 | tostring) + " cm"' "$1.eval.json" || echo "failed"
}

# The estimate [ms] at the first keyframe 10 s after the run's first one, and at the end (time_offset.csv).
estimate_at() {  # time_offset.csv
  awk '!/^#/ { if (t0 == "") t0 = $1; if (at10 == "" && $1 - t0 >= 10) at10 = $2; last = $2 }
       END { printf "%.1f / %.1f", at10, last }' "$1"
}

echo "| preset | offset [ms] | mode | ATE, offset unknown, held | ATE, offset given (timeshift_cam_imu) | ATE, offset estimated | estimate at 10 s / end [ms] |"
echo "|---|---|---|---|---|---|---|"
for preset in "${presets[@]}"; do
  for offset in $offsets; do
    mission=$cache/$preset-${duration}s-shift$offset
    if [[ ! -f $mission/mission.yaml ]]; then
      echo "rendering $preset with the camera clock shifted by $offset ms ..." >&2
      "$build/bin/cvislam_sim" --preset "$preset" --seed 1 --duration "$duration" --stereo --camera-clock-shift "$offset" \
        --out "$mission" --overwrite --quiet >&2
    fi
    sequence=$mission/agent0
    # The rig as Kalibr files, once as the synchronised rig and once with the offset as timeshift_cam_imu.
    kalibr=$cache/results/$preset-shift$offset-kalibr
    "$build/bin/cvislam_sensor_publisher" --dataset "$sequence" --write-calibration "$kalibr" 2> /dev/null
    sed -E "s/timeshift_cam_imu: .*/timeshift_cam_imu: $(awk "BEGIN{print $offset/1000}")/" \
      "$kalibr/camchain-imucam.yaml" > "$kalibr/camchain-shifted.yaml"
    for mode in mono stereo; do
      row=()
      for run in camchain-imucam:fixed camchain-shifted:fixed camchain-imucam:estimate; do
        chain=${run%:*}
        time_offset=${run#*:}
        out=$cache/results/$preset-shift$offset-$mode-$chain-$time_offset
        if "$build/bin/cvislam_agent" --dataset "$sequence" --mode "$mode" --pace sync --quiet --output "$out" \
            --calibration "$kalibr/$chain.yaml" --imu-calibration "$kalibr/imu.yaml" --time-offset "$time_offset" \
            --config <(printf 'imu:\n  noise_inflation: 1\n') > "$out.log" 2>&1; then
          row+=("$(ate "$out/trajectory.txt" "$sequence")")
        else
          row+=("agent failed: $out.log")
        fi
      done
      echo "| $preset | $offset | $mode | ${row[0]} | ${row[1]} | ${row[2]} | $(estimate_at "$out/time_offset.csv") |"
    done
  done
done
