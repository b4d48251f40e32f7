#!/usr/bin/env bash
# What a camera-IMU clock offset costs the agent: renders PRESET (each of SEEDS, stereo, agent0 scored) with the
# cameras' clock shifted by each OFFSET against the IMU (cvislam_sim --camera-clock-shift), then runs the agent at
# --pace sync, mono and stereo, three times per offset: with the offset unknown and held (the images' stamps taken as
# they are), given as Kalibr's timeshift_cam_imu, and unknown but estimated (--time-offset estimate, from 0). Scores the
# per-frame trajectory (SE3 ATE) against ground truth, and says where the estimate was 10 s into the run and at its end.
# Single runs of one sequence swing with small changes, so it ends with the estimated runs against the offset-free
# run of the same seed and mode over all seeds: how many within 1.2x, the geometric mean and the worst; and, as the
# yardstick, the same for estimating where there is no offset.
#
#   [DURATION=30] [OFFSETS="0 -20 10 30"] [SEEDS="1"] test/bench/clock_offset.sh [BUILD_DIR] [PRESET...]
#   (default presets: loop euroc-mh)
#
# Prints markdown tables; renders go to $CACHE (default /tmp/cvislam-clock), runs to $CACHE/results.
set -euo pipefail
cd "$(dirname "$0")/../.."
build=${1:-build/default}
shift || true
presets=("$@")
[[ ${#presets[@]} -gt 0 ]] || presets=(loop euroc-mh)
cache=${CACHE:-/tmp/cvislam-clock}
duration=${DURATION:-30}
offsets=${OFFSETS:-0 -20 10 30}
seeds=${SEEDS:-1}
mkdir -p "$cache/results"
scores=$(mktemp)
trap 'rm -f "$scores"' EXIT
for tool in cvislam_sim cvislam_agent cvislam_eval cvislam_sensor_publisher; do
  [[ -x $build/bin/$tool ]] || { echo "missing $build/bin/$tool: build it first" >&2; exit 1; }
done

ate_cm() {  # trajectory, sequence: the ATE in cm, or nothing when it cannot be scored
  "$build/bin/cvislam_eval" --estimate "$1" --groundtruth "$2" --json "$1.eval.json" -q > /dev/null 2>&1 &&
    jq -r '.se3.rmse * 10000 | round / 100' "$1.eval.json" || true
}

cm() { [[ -n $1 ]] && echo "$1 cm" || echo "failed"; }

# The estimate [ms] at the first keyframe 10 s after the run's first one, and at the end (time_offset.csv).
estimate_at() {  # time_offset.csv
  awk '!/^#/ { if (t0 == "") t0 = $1; if (at10 == "" && $1 - t0 >= 10) at10 = $2; last = $2 }
       END { printf "%.1f / %.1f", at10, last }' "$1"
}

echo "| preset | seed | offset [ms] | mode | ATE, offset unknown, held | ATE, offset given (timeshift_cam_imu) | ATE, offset estimated | estimate at 10 s / end [ms] |"
echo "|---|---|---|---|---|---|---|---|"
for preset in "${presets[@]}"; do
  for seed in $seeds; do
    for offset in $offsets; do
      # Seed 1 keeps the name it always had, so that its renders are reused.
      name=$preset$([[ $seed == 1 ]] || echo "-s$seed")
      mission=$cache/$name-${duration}s-shift$offset
      if [[ ! -f $mission/mission.yaml ]]; then
        echo "rendering $preset seed $seed with the camera clock shifted by $offset ms ..." >&2
        "$build/bin/cvislam_sim" --preset "$preset" --seed "$seed" --duration "$duration" --stereo \
          --camera-clock-shift "$offset" --out "$mission" --overwrite --quiet >&2
      fi
      sequence=$mission/agent0
      # The rig as Kalibr files, once as the synchronised rig and once with the offset as timeshift_cam_imu.
      kalibr=$cache/results/$name-shift$offset-kalibr
      "$build/bin/cvislam_sensor_publisher" --dataset "$sequence" --write-calibration "$kalibr" 2> /dev/null
      sed -E "s/timeshift_cam_imu: .*/timeshift_cam_imu: $(awk "BEGIN{print $offset/1000}")/" \
        "$kalibr/camchain-imucam.yaml" > "$kalibr/camchain-shifted.yaml"
      for mode in mono stereo; do
        row=()
        for run in camchain-imucam:fixed camchain-shifted:fixed camchain-imucam:estimate; do
          chain=${run%:*}
          time_offset=${run#*:}
          out=$cache/results/$name-shift$offset-$mode-$chain-$time_offset
          if "$build/bin/cvislam_agent" --dataset "$sequence" --mode "$mode" --pace sync --quiet --output "$out" \
              --calibration "$kalibr/$chain.yaml" --imu-calibration "$kalibr/imu.yaml" --time-offset "$time_offset" \
              --config <(printf 'imu:\n  noise_inflation: 1\n') > "$out.log" 2>&1; then
            row+=("$(ate_cm "$out/trajectory.txt" "$sequence")")
          else
            row+=("")
            echo "agent failed: $out.log" >&2
          fi
        done
        printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$preset" "$seed" "$offset" "$mode" "${row[0]:-nan}" "${row[1]:-nan}" \
          "${row[2]:-nan}" >> "$scores"
        echo "| $preset | $seed | $offset | $mode | $(cm "${row[0]}") | $(cm "${row[1]}") | $(cm "${row[2]}") |" \
          "$(estimate_at "$out/time_offset.csv") |"
      done
    done
  done
done

# Estimated against the offset-free run (offset 0, held) of the same preset, seed and mode.
echo
echo "| runs | estimated ATE within 1.2x of the offset-free run | geometric mean of the ratio | worst |"
echo "|---|---|---|---|"
awk -F'\t' '
  $3 == 0 { free[$1 FS $2 FS $4] = $5 }
  { row[NR] = $0 }
  END {
    for (i = 1; i <= NR; ++i) {
      split(row[i], f, FS)
      base = free[f[1] FS f[2] FS f[4]]
      kind = f[3] == 0 ? "no offset, estimated anyway" : "with an offset"
      if (base == "" || base == "nan" || f[7] == "nan" || base <= 0) { ++failed[kind]; continue }
      r = f[7] / base
      ++n[kind]; within[kind] += r <= 1.2; logs[kind] += log(r); if (r > worst[kind]) worst[kind] = r
    }
    for (kind in n)
      printf "| %s: %d%s | %d | %.2f | %.2fx |\n", kind, n[kind], failed[kind] ? " (" failed[kind] " not scored)" : "",
             within[kind], exp(logs[kind] / n[kind]), worst[kind]
  }' "$scores"
