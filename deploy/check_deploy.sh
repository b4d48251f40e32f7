#!/usr/bin/env bash
# Checks the deployment files offline (no container engine, no cluster): lints the container files, renders
# every kustomization with `kubectl kustomize` and validates each object against the Kubernetes schemas and
# the project's rules (deploy/k8s/validate.mjs), ending with "N passed, N failed". Also checks that the
# validator still refuses every object of deploy/k8s/testdata/broken.yaml, and the Grafana dashboard's queries
# against the metrics the server exports (deploy/grafana/check_dashboard.py). The metrics an HPA or a
# prometheus-adapter rule names are checked against those too (validate.mjs --metrics-source). CTest runs it
# (deploy_manifests).
#
#   deploy/check_deploy.sh [--keep DIR]     --keep: write the rendered manifests to DIR
#
# Needs the tools of deploy/install_deploy_tools.sh (out/deploy-tools, or $CVISLAM_DEPLOY_TOOLS), and kubectl.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
tools=${CVISLAM_DEPLOY_TOOLS:-$repo/out/deploy-tools}
keep=""
if [ "${1:-}" = "--keep" ]; then keep=$2; fi
if [ ! -d "$tools/node_modules/kubernetes-models" ] || ! command -v kubectl >/dev/null 2>&1; then
  echo "check_deploy: tools missing in $tools (or no kubectl): run deploy/install_deploy_tools.sh" >&2
  exit 1
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rc=0

echo "== container files (dockerfilelint)"
for f in "$repo"/deploy/docker/*.Dockerfile; do
  if (cd "$tools" && node node_modules/dockerfilelint/bin/dockerfilelint "$f" >"$work/lint.txt" 2>&1); then
    echo "ok    $(basename "$f")"
  else
    echo "FAIL  $(basename "$f")"; sed 's/^/        /' "$work/lint.txt"; rc=1
  fi
done

echo "== Kubernetes manifests (kubectl kustomize, then kubernetes-models and the project's rules)"
# Render from a copy with throwaway secrets, so that the repository's own secrets folders stay untouched.
cp -r "$repo/deploy/k8s" "$work/k8s"
rm -rf "$work"/k8s/overlays/*/secrets "$work/k8s/agent-example/secrets"
"$work/k8s/make_secrets.sh" --missions survey,depot >/dev/null
rendered=()
for k in "$work"/k8s/overlays/* "$work/k8s/agent-example"; do
  name=$(basename "$k")
  if ! kubectl kustomize "$k" > "$work/$name.yaml" 2>"$work/kustomize.err"; then
    echo "FAIL  kubectl kustomize ${k#"$work/"}:"; sed 's/^/        /' "$work/kustomize.err"; rc=1; continue
  fi
  rendered+=("$work/$name.yaml")
done
cp "$repo/deploy/k8s/validate.mjs" "$tools/validate.mjs"
# The metrics an HPA or a prometheus-adapter rule may name: those the server exports.
metrics_source="$repo/server_cloud/service/metrics_endpoint.cpp"
node "$tools/validate.mjs" --metrics-source "$metrics_source" "${rendered[@]}" || rc=1

# The validator must still catch what it is for.
broken_total=$(grep -c '^kind:' "$repo/deploy/k8s/testdata/broken.yaml")
node "$tools/validate.mjs" --metrics-source "$metrics_source" "$repo/deploy/k8s/testdata/broken.yaml" \
  > "$work/broken.txt" || true
broken_refused=$(grep -c '^FAIL' "$work/broken.txt" || true)
echo "validator self-test: $broken_refused of $broken_total broken objects refused (deploy/k8s/testdata/broken.yaml)"
if [ "$broken_refused" -ne "$broken_total" ]; then
  grep '^ok' "$work/broken.txt" | sed 's/^/  not refused: /'; rc=1
fi

echo "== Grafana dashboard (deploy/grafana): its queries against the metrics the server exports"
python3 "$repo/deploy/grafana/check_dashboard.py" "$repo/deploy/grafana/cvislam-server.json" \
  "$repo/server_cloud/service/metrics_endpoint.cpp" --self-test || rc=1
if [ -n "$keep" ]; then mkdir -p "$keep" && cp "${rendered[@]}" "$keep/"; fi
exit "$rc"
