#!/usr/bin/env bash
# Runs every fuzz target of test/fuzz with libFuzzer: configures build/fuzz with clang-14 (coverage
# instrumentation and AddressSanitizer everywhere), builds only the fuzz targets and what they link, writes each
# target's seeds, and runs it for --runs inputs. Crash inputs land in build/fuzz/artifacts/<target>/; the corpus
# grows in build/fuzz/corpus/<target>/ and is reused by the next run.
#
#   test/fuzz/run_fuzz.sh [--runs N] [--target NAME] [--max-len BYTES]     (default: 1000000 inputs, every target)
#
# Prints one line per target: inputs run, coverage, corpus size, crashes. Exit status 1 when a target crashed.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."

runs=1000000
max_len=65536
targets=(fuzz_agent_link fuzz_map_service fuzz_store_records fuzz_mcap_reader)
while [ $# -gt 0 ]; do
  case "$1" in
    --runs) runs="$2"; shift 2 ;;
    --target) targets=("$2"); shift 2 ;;
    --max-len) max_len="$2"; shift 2 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "run_fuzz.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
if ! command -v clang++-14 >/dev/null || [ ! -f /usr/lib/llvm-14/lib/clang/14.0.6/lib/linux/libclang_rt.fuzzer-x86_64.a ]; then
  echo "run_fuzz.sh: clang-14 with libFuzzer is missing: run deploy/install_deps.sh (clang, libclang-rt-14-dev)" >&2
  exit 2
fi

build=build/fuzz
if [ ! -f "$build/build.ninja" ]; then
  CC=clang-14 CXX=clang++-14 cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
    -DCVISLAM_FUZZ=ON -DCVISLAM_SANITIZE=address -DCVISLAM_WERROR=OFF -DCVISLAM_BUILD_BENCHMARKS=OFF >/dev/null
fi
cmake --build "$build" --target "${targets[@]}"

failed=0
for t in "${targets[@]}"; do
  corpus="$build/corpus/$t"
  artifacts="$build/artifacts/$t/"
  mkdir -p "$corpus" "$artifacts"
  CVISLAM_FUZZ_WRITE_SEEDS="$corpus" "$build/fuzz/$t" >/dev/null
  log="$build/$t.log"
  start=$(date +%s)
  set +e
  ASAN_OPTIONS=detect_leaks=1 "$build/fuzz/$t" -runs="$runs" -max_len="$max_len" -use_value_profile=1 \
    -print_final_stats=1 -artifact_prefix="$artifacts" "$corpus" >"$log" 2>&1
  rc=$?
  set -e
  seconds=$(( $(date +%s) - start ))
  done_runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo "?")
  cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | grep -o '[0-9]*' || echo "?")
  crashes=$(find "$artifacts" -type f | wc -l)
  echo "$t: $done_runs inputs in ${seconds} s, coverage $cov edges, corpus $(ls "$corpus" | wc -l) inputs, $crashes crash inputs (exit $rc; log $log)"
  if [ "$rc" -ne 0 ] || [ "$crashes" -ne 0 ]; then failed=1; fi
done
exit "$failed"
