#!/usr/bin/env bash
# Makes the secrets the Kubernetes manifests read, so that they never live in the repository:
#   overlays/single/secrets/tokens    one 'MISSION TOKEN' line per mission (fresh random tokens), mode 600
#   overlays/single/secrets/tls.{crt,key}  a self-signed certificate for the server's Service names
#   overlays/scaleout/secrets/            the same tokens and certificate, and postgres-password (random)
#   agent-example/secrets/{token,ca.crt}   the first mission's token and the certificate to trust
#
#   deploy/k8s/make_secrets.sh --missions survey,depot [--namespace cvislam] [--root DIR] [--force]
#
# A real deployment brings its own certificate (from its CA) and token file: put them at the same paths.
# Existing files are kept unless --force, so running it twice changes nothing.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
missions=""
namespace=cvislam
force=0
while [ $# -gt 0 ]; do
  case "$1" in
    --missions) missions=$2; shift 2 ;;
    --namespace) namespace=$2; shift 2 ;;
    --root) root=$2; shift 2 ;;
    --force) force=1; shift ;;
    -h|--help) sed -n '2,14p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "make_secrets: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
if [ -z "$missions" ]; then
  echo "make_secrets: give --missions NAME[,NAME...] (the missions the tokens open)" >&2
  exit 2
fi
command -v openssl >/dev/null || { echo "make_secrets: needs openssl (apt-get install openssl)" >&2; exit 1; }

server_dir="$root/overlays/single/secrets"
scaleout_dir="$root/overlays/scaleout/secrets"
agent_dir="$root/agent-example/secrets"
if [ "$force" -eq 0 ] && [ -f "$server_dir/tokens" ] && [ -f "$server_dir/tls.crt" ] && [ -f "$agent_dir/token" ] &&
  [ -f "$scaleout_dir/postgres-password" ]; then
  echo "make_secrets: secrets already in $server_dir, $scaleout_dir and $agent_dir (--force to make new ones)"
  exit 0
fi
umask 077
mkdir -p "$server_dir" "$scaleout_dir" "$agent_dir"
: > "$server_dir/tokens"
first_token=""
IFS=, read -r -a names <<< "$missions"
for m in "${names[@]}"; do
  if ! [[ "$m" =~ ^[A-Za-z0-9._-]+$ ]]; then
    echo "make_secrets: mission name '$m': use letters, digits, . _ -" >&2
    exit 2
  fi
  token=$(openssl rand -hex 24)
  echo "$m $token" >> "$server_dir/tokens"
  first_token=${first_token:-$token}
done
svc=cvislam-server
sans="DNS:$svc,DNS:$svc.$namespace,DNS:$svc.$namespace.svc,DNS:*.$svc-headless.$namespace.svc,DNS:localhost,IP:127.0.0.1"
openssl req -x509 -newkey rsa:2048 -nodes -days 365 -subj "/CN=$svc" -addext "subjectAltName=$sans" \
  -keyout "$server_dir/tls.key" -out "$server_dir/tls.crt" 2>/dev/null
printf '%s' "$first_token" > "$agent_dir/token"
cp "$server_dir/tls.crt" "$agent_dir/ca.crt"
cp "$server_dir/tokens" "$server_dir/tls.crt" "$server_dir/tls.key" "$scaleout_dir/"
printf '%s' "$(openssl rand -hex 24)" > "$scaleout_dir/postgres-password"
echo "make_secrets: ${#names[@]} mission token(s) and a self-signed certificate for $svc.$namespace in $server_dir;"
echo "  the same and the database password in $scaleout_dir;"
echo "  the agent example's token (mission ${names[0]}) and CA in $agent_dir"
