#!/usr/bin/env bash
# Installs the npm tools of the offline checks, from the npm registry, into out/deploy-tools (never into the
# repository): for the deployment files kubernetes-models (Kubernetes schemas), yaml, dockerfilelint; for the
# MCAP and ROS 2 interop test (test/common/mcap/interop_test.mjs) @mcap/core, @mcap/nodejs, @mcap/support,
# @foxglove/wasm-zstd, @foxglove/rosmsg and @foxglove/rosmsg2-serialization; for the live viewer three.js (which
# the server serves to browsers), and for its tests @foxglove/ws-protocol, @foxglove/schemas, ws, ajv,
# puppeteer-core and pngjs, with Debian's chromium. Versions are pinned in
# deploy/tools/package.json. Idempotent: with the same versions installed it returns at once, offline.
#
#   deploy/install_deploy_tools.sh [--dir DIR]      (default: out/deploy-tools, or $CVISLAM_DEPLOY_TOOLS)
#
# Needs node and npm (Debian: nodejs npm; installed here when missing) and kubectl for `kubectl kustomize`.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
dir=${CVISLAM_DEPLOY_TOOLS:-$repo/out/deploy-tools}
if [ "${1:-}" = "--dir" ]; then dir=$2; fi

if ! command -v npm >/dev/null 2>&1; then
  echo "install_deploy_tools: installing nodejs and npm from Debian" >&2
  sudo_cmd=()
  if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends nodejs npm >&2
fi
# The viewer's browser test runs the page in Debian's Chromium (headless, software WebGL) through puppeteer-core.
if ! command -v chromium >/dev/null 2>&1; then
  echo "install_deploy_tools: installing chromium from Debian (the viewer's browser test)" >&2
  sudo_cmd=()
  if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends chromium >&2
fi
if ! command -v kubectl >/dev/null 2>&1; then
  echo "install_deploy_tools: kubectl not found. The manifest check renders with 'kubectl kustomize' (kubectl" \
       ">= 1.27; Debian's kubernetes-client 1.20 has a kustomize too old for these files)." >&2
  exit 1
fi

if [ -f "$dir/.stamp" ] && cmp -s "$dir/.stamp" "$repo/deploy/tools/package.json" && [ -d "$dir/node_modules" ]; then
  echo "install_deploy_tools: present in $dir"
  exit 0
fi
mkdir -p "$dir"
cp "$repo/deploy/tools/package.json" "$dir/package.json"
echo "install_deploy_tools: npm install into $dir" >&2
(cd "$dir" && npm install --no-audit --no-fund --loglevel=error >&2)
cp "$repo/deploy/tools/package.json" "$dir/.stamp"
echo "install_deploy_tools: done ($dir)"
