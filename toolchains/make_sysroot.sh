#!/usr/bin/env bash
# Builds (once) and caches a Debian 12 sysroot for cross-compiling the agent to a board, and installs the host
# tools that cross-building and running the result under qemu need.
#
#   toolchains/make_sysroot.sh [--arch arm64] [--dir DIR] [--check]
#
#   --arch   Debian architecture of the board (arm64 is the one the project builds and tests)
#   --dir    where the sysroot goes (default: out/sysroot/<arch>-bookworm in the repository, or $CVISLAM_SYSROOT)
#   --check  only say whether the cached sysroot is complete and current; exit 1 if not
#
# Prints the sysroot's path as its last line. Idempotent: a sysroot made from the same package list is reused
# (a stamp file records the list), so a second run returns in well under a second without the network.
#
# Why a sysroot and not multiarch: installing libceres-dev:arm64, libyaml-cpp-dev:arm64 or the arm64 OpenCV
# features2d/calib3d/imgcodecs packages next to the amd64 ones makes apt REMOVE the amd64 ones (their -dev
# dependencies are not Multi-Arch: same). mmdebstrap --variant=extract unpacks the packages into one folder
# without running maintainer scripts, so the host stays untouched.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
arch=arm64
dir=""
check=0
while [ $# -gt 0 ]; do
  case "$1" in
    --arch) arch=$2; shift 2 ;;
    --dir) dir=$2; shift 2 ;;
    --check) check=1; shift ;;
    -h|--help) sed -n '2,17p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "make_sysroot: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
case "$arch" in
  arm64) triple=aarch64-linux-gnu ;;
  *) echo "make_sysroot: --arch '$arch' is not supported; the project cross-builds for arm64 (x86 boards build natively with the board-x86-64-v3 preset)" >&2; exit 2 ;;
esac
dir=${dir:-${CVISLAM_SYSROOT:-$repo/out/sysroot/$arch-bookworm}}

# What the agent, common and their tests link, as arm64 packages (the server is not built for boards).
# Keep in step with deploy/install_deps.sh and toolchains/cmake/CvislamDependencies.cmake.
packages=(
  libc6-dev libstdc++-12-dev
  libeigen3-dev libceres-dev
  libopencv-core-dev libopencv-imgproc-dev libopencv-features2d-dev libopencv-calib3d-dev libopencv-imgcodecs-dev
  libdeflate-dev libzstd-dev liblz4-dev zlib1g-dev
  libgrpc++-dev libprotobuf-dev
  libiceoryx-posh-dev libiceoryx-hoofs-dev libacl1-dev
  libyaml-cpp-dev libcli11-dev libfmt-dev nlohmann-json3-dev
  libgtest-dev libgmock-dev libbenchmark-dev
)
host_tools=(mmdebstrap "g++-$triple" qemu-user protobuf-compiler protobuf-compiler-grpc)

stamp="$dir/.cvislam-sysroot"
want="arch=$arch packages=${packages[*]}"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  if [ "$check" -eq 1 ]; then echo "make_sysroot: $dir is complete"; fi
  echo "$dir"
  exit 0
fi
if [ "$check" -eq 1 ]; then
  echo "make_sysroot: no current sysroot at $dir (run toolchains/make_sysroot.sh)" >&2
  exit 1
fi

missing=()
for p in "${host_tools[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q '^install ok installed$'; then missing+=("$p"); fi
done
if [ "${#missing[@]}" -gt 0 ]; then
  sudo_cmd=()
  if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi
  echo "make_sysroot: installing host tools: ${missing[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  if ! "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}" >&2; then
    "${sudo_cmd[@]}" apt-get update -q >&2
    "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}" >&2
  fi
fi

# The mirror the machine already uses (deb822 or one-line sources), so that no other network is needed.
mirror=$( (grep -hsE '^(URIs:|deb )' /etc/apt/sources.list.d/*.sources /etc/apt/sources.list || true) |
         grep -v security | head -1 | sed -E 's/^URIs:[[:space:]]*//; s/^deb (\[[^]]*\] )?//; s/[[:space:]].*$//')
mirror=${mirror:-http://deb.debian.org/debian}

start=$(date +%s)
echo "make_sysroot: building the $arch sysroot in $dir from $mirror (${#packages[@]} packages and their dependencies)" >&2
rm -rf "$dir.partial"
mkdir -p "$(dirname "$dir")"
include=$(IFS=,; echo "${packages[*]}")
mmdebstrap --quiet --variant=extract --arch="$arch" --include="$include" bookworm "$dir.partial" "$mirror" >&2

# What maintainer scripts would have done and the build needs:
# (a) BLAS/LAPACK are chosen by update-alternatives, which extract does not run; point the names at ATLAS
#     or, failing that, the reference implementation.
libdir="$dir.partial/usr/lib/$triple"
for l in libblas.so libblas.so.3 liblapack.so liblapack.so.3; do
  if [ ! -e "$libdir/$l" ]; then
    for impl in atlas blas lapack openblas-pthread; do
      if [ -e "$libdir/$impl/$l" ]; then ln -sf "$impl/$l" "$libdir/$l"; break; fi
    done
  fi
done
# (b) Absolute symlinks inside the sysroot would point into the host; make them relative.
find "$dir.partial" -type l -lname '/*' | while read -r link; do
  target=$(readlink "$link")
  ln -sfn "$(realpath -m --relative-to="$(dirname "$link")" "$dir.partial$target")" "$link"
done
# (c) gRPC's exported targets expect its code generators in the sysroot's /usr/bin and check that they exist;
#     the build runs the host's (protobuf-compiler-grpc), so link those in.
for plugin in grpc_cpp_plugin grpc_csharp_plugin grpc_node_plugin grpc_objective_c_plugin grpc_php_plugin \
              grpc_python_plugin grpc_ruby_plugin; do
  ln -sfn "/usr/bin/$plugin" "$dir.partial/usr/bin/$plugin"
done
rm -rf "$dir"
mv "$dir.partial" "$dir"
echo "$want" > "$stamp"
echo "make_sysroot: done in $(( $(date +%s) - start )) s, $(du -sh "$dir" | cut -f1)" >&2
echo "$dir"
