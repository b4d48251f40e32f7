#!/usr/bin/env bash
# Installs the Debian 12 packages that building and testing cvislam need, and nothing else.
# Idempotent: when everything is already installed it checks with dpkg and returns in well under a second,
# without touching the network. Run as root (or with sudo available).
#
#   deploy/install_deps.sh            # build + test dependencies
#   deploy/install_deps.sh --check    # only report what is missing; exit 1 if anything is
set -euo pipefail

# Keep this list in step with toolchains/cmake/CvislamDependencies.cmake.
packages=(
  # toolchain
  cmake ninja-build g++ ccache pkg-config
  # maths and optimisation
  libeigen3-dev libceres-dev
  # BLAS for CHOLMOD (the server's global BA on a dense map is mostly its supernodal factorisation): OpenBLAS,
  # 2x faster there than the ATLAS that libceres-dev pulls in. The serial build, so that its threads never
  # spin on cores the server's other workers need.
  libopenblas0-serial
  # OpenCV, per module: OpenCVConfig.cmake ships only in libopencv-dev (+330 MB of VTK, dnn, contrib),
  # so we take the modules we use and toolchains/cmake/OpenCVMinimal.cmake makes the targets.
  libopencv-core-dev libopencv-imgproc-dev libopencv-features2d-dev libopencv-calib3d-dev libopencv-imgcodecs-dev
  # the agent's PNG decoding (common/dataset/png_gray.cpp)
  libdeflate-dev
  # MCAP files (common/mcap): zstd and LZ4 chunk compression, zlib's CRC-32
  libzstd-dev liblz4-dev zlib1g-dev
  # agent <-> server link and the map service
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  # the server's map store; openssl makes the throwaway certificate of the TLS tests
  libsqlite3-dev openssl
  # scale-out: the replicas' shared store and mission leases in PostgreSQL (libpq; the tests start a throwaway
  # cluster with postgresql-15's initdb and pg_ctl)
  libpq-dev postgresql-15
  # the server's metrics endpoint (Prometheus text format over HTTP); the Prometheus parser and curl its tests use
  prometheus-cpp-dev python3-prometheus-client curl
  # the live viewer's endpoint (Foxglove WebSocket protocol and the page over HTTP, TLS by OpenSSL)
  libwebsocketpp-dev libasio-dev libssl-dev
  # fuzzing the server's inbound messages with libFuzzer (test/fuzz/run_fuzz.sh)
  clang libclang-rt-14-dev
  # the style check (test/check_style.sh): formatting in CI, clang-tidy on changed files
  clang-format clang-tidy
  # the map service's Python client (server_cloud/tools/cvislam_map_client.py) and its test
  python3-grpcio python3-protobuf
  # zero-copy tracking <-> mapping; libacl1-dev because iceoryx's RouDi headers include <sys/acl.h>
  libiceoryx-posh-dev libiceoryx-hoofs-dev iceoryx libacl1-dev
  # config, CLI, output
  libyaml-cpp-dev libcli11-dev libfmt-dev nlohmann-json3-dev
  # tests and benchmarks
  libgtest-dev libgmock-dev libbenchmark-dev
  # deploy/run_mission.sh's report (tools/mission_report.py, standard library only); jq for
  # test/bench/agent_accuracy.sh
  python3 jq
  # the chaos suite (test/chaos/run_chaos.py): network namespaces and tc, and a server clock that jumps
  iproute2 faketime
)

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q '^install ok installed$'; then
    missing+=("$p")
  fi
done

if [ "${#missing[@]}" -eq 0 ]; then
  echo "install_deps: all ${#packages[@]} packages present"
  exit 0
fi
if [ "${1:-}" = "--check" ]; then
  echo "install_deps: missing: ${missing[*]}" >&2
  exit 1
fi

sudo_cmd=()
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null 2>&1; then
    sudo_cmd=(sudo)
  else
    echo "install_deps: need root to install: ${missing[*]} (run as root or install sudo)" >&2
    exit 1
  fi
fi

echo "install_deps: installing ${#missing[@]} package(s): ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
# Update the package lists only when apt has never fetched them on this machine, or when an install fails
# because they are stale.
if ! compgen -G "/var/lib/apt/lists/*_Packages" >/dev/null; then
  "${sudo_cmd[@]}" apt-get update -q
fi
if ! "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}"; then
  "${sudo_cmd[@]}" apt-get update -q
  "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}"
fi
echo "install_deps: done"
