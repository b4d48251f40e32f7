#!/usr/bin/env bash
# The viewer's endpoint of a real cvislam_server process, without agents: what the port serves over HTTP (the page,
# three.js, 404 for anything else and for paths that try to leave the served folders), upgrades refused with 401
# (wrong or missing token) and 400 (no Foxglove subprotocol), hostile client messages answered with a status while
# the connection stays usable, and the same over TLS (https and wss with the server's certificate; plain http to
# the TLS port fails). Node's reference client does the WebSocket part (endpoint_client.mjs).
#
#   endpoint_test.sh REPO SERVER_BINARY
set -euo pipefail
repo=$1
server_bin=$2
tools=${CVISLAM_DEPLOY_TOOLS:-$repo/out/deploy-tools}
tmp=$(mktemp -d)
server=""
cleanup() {
  [ -z "$server" ] || { kill -TERM "$server" 2>/dev/null; wait "$server" 2>/dev/null; } || true
  rm -rf "$tmp"
}
trap cleanup EXIT
fail() { echo "endpoint_test: $*" >&2; cat "$tmp/server.log" >&2 || true; exit 1; }
token=0123456789abcdef0123456789abcdef
printf 'survey %s\n' "$token" >"$tmp/tokens"
# A page folder of its own (a file beside it must not be reachable) and three.js from the npm tools.
mkdir -p "$tmp/page"
echo '<html>viewer page</html>' >"$tmp/page/index.html"
echo 'secret' >"$tmp/secret.txt"

start() {  # start SCHEME [server args...]
  rm -f "$tmp/viewer.port"
  "$server_bin" --listen 127.0.0.1:0 --quiet --no-recognition --no-backend --tokens "$tmp/tokens" \
    --viewer-listen 127.0.0.1:0 --viewer-port-file "$tmp/viewer.port" --viewer-dir "$tmp/page" \
    --viewer-three "$tools/node_modules/three/build" "$@" >"$tmp/server.log" 2>&1 &
  server=$!
  for _ in $(seq 100); do [ -f "$tmp/viewer.port" ] && break; sleep 0.1; done
  [ -f "$tmp/viewer.port" ] || fail "the server did not start its viewer"
  port=$(cat "$tmp/viewer.port")
}
stop() { kill -TERM "$server"; wait "$server" || fail "the server did not stop cleanly"; server=""; }
status_of() { curl -s -o /dev/null -w '%{http_code}' "$@" || true; }

check_http() {  # check_http SCHEME CURL_ARGS...
  local scheme=$1; shift
  [ "$(curl -sf "$@" "$scheme://127.0.0.1:$port/")" = '<html>viewer page</html>' ] || fail "$scheme: / is not the page"
  curl -sf "$@" "$scheme://127.0.0.1:$port/three/three.module.js" -o /dev/null || fail "$scheme: three.js not served"
  [ "$(status_of "$@" "$scheme://127.0.0.1:$port/nope.js")" = 404 ] || fail "$scheme: a missing file is not 404"
  [ "$(status_of "$@" --path-as-is "$scheme://127.0.0.1:$port/../secret.txt")" = 404 ] ||
    fail "$scheme: a path out of the page folder is not refused"
  [ "$(status_of "$@" --path-as-is "$scheme://127.0.0.1:$port/three/../../secret.txt")" = 404 ] ||
    fail "$scheme: a path out of three's folder is not refused"
}

start
check_http http
node "$repo/test/viewer/endpoint_client.mjs" --url "ws://127.0.0.1:$port/" --mission survey --token "$token" \
  --tools "$tools" || fail "the WebSocket checks failed over ws"
stop

openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=localhost \
  -addext subjectAltName=DNS:localhost,IP:127.0.0.1 -keyout "$tmp/key.pem" -out "$tmp/cert.pem" 2>/dev/null
start --tls-cert "$tmp/cert.pem" --tls-key "$tmp/key.pem"
grep -q "https://HOST" "$tmp/server.log" || fail "the server does not say the viewer speaks https"
check_http https --cacert "$tmp/cert.pem"
[ "$(status_of "http://127.0.0.1:$port/")" = 000 ] || fail "plain http was answered on the TLS port"
NODE_EXTRA_CA_CERTS="$tmp/cert.pem" node "$repo/test/viewer/endpoint_client.mjs" --url "wss://127.0.0.1:$port/" \
  --mission survey --token "$token" --tools "$tools" || fail "the WebSocket checks failed over wss"
stop
echo "endpoint_test: http and https, ws and wss: all checks passed"
