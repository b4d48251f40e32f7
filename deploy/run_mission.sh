#!/usr/bin/env bash
# The project's main job, end to end: install what is missing, build, run, print the result table.
#
# Today the richest end-to-end run is the evaluation pipeline on real data: the eight real visual-inertial
# estimates of rpg_trajectory_evaluation's EuRoC set (MH_01/03/05 and V2_01, mono and stereo) and evo's
# V1_02 estimate, each scored by cvislam_eval against EuRoC ground truth; then cvislam_agent itself,
# stereo-inertial on the real V1_01 excerpt. It becomes the collaborative mission (server + agents over
# loopback gRPC) when the server lands.
#
#   deploy/run_mission.sh [--out DIR] [--build-dir DIR]
#
# Data: $CVISLAM_DATA_DIR, else ../shared/data beside the repository. Results: DIR (default out/mission):
# one JSON and one SVG top view per run, and summary.tsv.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
out="$repo/out/mission"
build="$repo/build/default"
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out=$2; shift 2 ;;
    --build-dir) build=$2; shift 2 ;;
    -h|--help) sed -n '2,13p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "run_mission: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done

"$repo/deploy/install_deps.sh"

echo "== build (preset 'default' in $build)"
if [ ! -f "$build/build.ninja" ]; then
  cmake -S "$repo" --preset default -B "$build" >/dev/null
fi
cmake --build "$build" --target cvislam_eval cvislam_agent
eval_bin="$build/bin/cvislam_eval"
agent_bin="$build/bin/cvislam_agent"

data=${CVISLAM_DATA_DIR:-"$repo/../shared/data"}
if [ ! -d "$data/peer-rpg" ] || [ ! -d "$data/euroc-groundtruth" ]; then
  echo "run_mission: SKIPPED the evaluation: real data not found under '$data'" >&2
  echo "  (it needs peer-rpg/, peer-evo/ and euroc-groundtruth/; set CVISLAM_DATA_DIR to the shared data folder)" >&2
  exit 0
fi
data=$(cd "$data" && pwd)
mkdir -p "$out"

# name | estimate | ground truth | association | max diff [s]
runs=()
for mode in mono stereo; do
  for seq in MH_01:MH_01_easy MH_03:MH_03_medium MH_05:MH_05_difficult V2_01:V2_01_easy; do
    short=${seq%%:*}; full=${seq#*:}
    runs+=("vio_${mode}_${short}|$data/peer-rpg/vio_$mode/laptop_vio_${mode}_$short/stamped_traj_estimate.txt|$data/euroc-groundtruth/$full.txt|nearest|0.02")
  done
done
runs+=("evo_V1_02|$data/peer-evo/V102.txt|$data/peer-evo/V102_groundtruth.csv|nearest|0.01")

echo "== evaluate ${#runs[@]} real VIO runs against EuRoC ground truth"
printf 'run\tposes\tpath_m\tate_posyaw_m\tate_se3_m\tate_sim3_m\tscale_err_pct\trot_se3_deg\n' >"$out/summary.tsv"
i=0
for r in "${runs[@]}"; do
  IFS='|' read -r name est gt assoc maxdiff <<<"$r"
  i=$((i + 1))
  printf '  [%d/%d] %s\n' "$i" "${#runs[@]}" "$name"
  "$eval_bin" --quiet --estimate "$est" --groundtruth "$gt" --associate "$assoc" --max-diff "$maxdiff" \
    --json "$out/$name.json" --plot "$out/$name.svg" 2>"$out/$name.log" ||
    { echo "run_mission: cvislam_eval failed on $name:" >&2; cat "$out/$name.log" >&2; exit 1; }
  jq -r --arg n "$name" '[$n, .poses, (.groundtruth_path_m*100|round/100), .posyaw.rmse, .se3.rmse, .sim3.rmse,
      .scale_error_percent, .se3.rotation_deg.rmse] | @tsv' "$out/$name.json" >>"$out/summary.tsv"
done

echo
awk -F'\t' 'NR == 1 { printf "%-16s %6s %8s %13s %11s %12s %11s %12s\n", "run", "poses", "path[m]",
                      "ATE posyaw[m]", "ATE SE3[m]", "ATE Sim3[m]", "scale err%", "rot SE3[deg]"; next }
            { printf "%-16s %6d %8.1f %13.4f %11.4f %12.4f %+11.2f %12.3f\n", $1, $2, $3, $4, $5, $6, $7, $8 }' \
  "$out/summary.tsv"

# Our own agent on real images: stereo-inertial VIO over the real EuRoC V1_01 excerpt (4.7 s, the drone
# almost still), tracking and mapping joined by iceoryx inside one process.
if [ -d "$data/euroc-v101-excerpt/mav0" ]; then
  echo
  echo "== cvislam_agent: stereo-inertial on the real EuRoC V1_01 excerpt"
  "$agent_bin" --dataset "$data/euroc-v101-excerpt" --output "$out/agent_v101" --mode stereo --pace sync --quiet \
    >"$out/agent_v101.log" 2>&1 || { echo "run_mission: cvislam_agent failed:" >&2; tail -5 "$out/agent_v101.log" >&2; exit 1; }
  grep -E '^(frames|IMU|stage|orb|matching|pose|motion|keyframe_|tracking|local|mapping)' "$out/agent_v101.log"
  "$eval_bin" --quiet --estimate "$out/agent_v101/trajectory.txt" --groundtruth "$data/euroc-v101-excerpt" \
    --json "$out/agent_v101.json" >/dev/null 2>&1 || true
  jq -r '"ATE (SE3) \(.se3.rmse * 10000 | round / 10) mm over \(.poses) frames, ground-truth path \(.groundtruth_path_m * 100 | round / 100) m"' \
    "$out/agent_v101.json" 2>/dev/null || echo "(evaluation failed: see $out/agent_v101.log)"
fi

echo
echo "results: $out (summary.tsv, per-run JSON and SVG top views, agent_v101/)"
