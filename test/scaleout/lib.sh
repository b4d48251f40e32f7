# shellcheck shell=bash
# Shared by the scale-out scripts (sourced, with `repo` set): a work folder that the postgres user can enter, the
# processes started into `pids`, and a cleanup at exit that kills them, stops the database under "$work/pg" and
# removes the folder (unless `keep` is 1: then it says where the logs are); and deploy/lib/wait.sh's waits.
source "$repo/deploy/lib/wait.sh"
scaleout_work() {  # scaleout_work NAME: sets `work`, `pids` and the exit trap
  work=$(mktemp -d "/tmp/cvislam-$1.XXXXXX")
  chmod 755 "$work"  # the postgres user runs the database under it
  pids=()
  trap scaleout_cleanup EXIT
}
scaleout_cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null || true; wait "$p" 2>/dev/null || true; done
  "$repo/deploy/local_postgres.sh" stop "$work/pg" >/dev/null 2>&1 || true
  if [ "${keep:-0}" = 0 ]; then rm -rf "$work"; else echo "logs kept in $work"; fi
}
port() { python3 -c 'import socket;s=socket.socket();s.bind(("127.0.0.1",0));print(s.getsockname()[1])'; }
