#!/usr/bin/env bash
# Run a command with a Docker daemon: the running one, or one started here (root) and stopped
# when the command ends, however it ends (exit, error, Ctrl-C, SIGTERM).
#
#   scripts/with_dockerd.sh make test-containers
#
# A daemon started here keeps its images in the default /var/lib/docker, so a later run finds
# the image's layers cached. It gets no bridge network (--bridge=none, no iptables rules): its
# containers have loopback only, or the host's network where they ask for it
# (docker-compose.test.yml), and an offline build needs no network at all.
set -euo pipefail

[ $# -gt 0 ] || { echo "usage: scripts/with_dockerd.sh COMMAND [ARG...]" >&2; exit 2; }

if docker info >/dev/null 2>&1; then
  exec "$@"
fi
[ "$(id -u)" = 0 ] || { echo "with_dockerd.sh: no Docker daemon running, and not root" >&2; exit 1; }
command -v dockerd >/dev/null || { echo "with_dockerd.sh: dockerd is missing" >&2; exit 1; }

log="$(mktemp /tmp/tupa-dockerd.XXXXXX.log)"
dockerd --bridge=none --iptables=false --ip-masq=false >"$log" 2>&1 &
pid=$!
stop_dockerd() {
  if kill -0 "$pid" 2>/dev/null; then
    kill -TERM "$pid" 2>/dev/null || true
    # dockerd stops its containers (10 s each at most) and its containerd, then exits.
    for _ in $(seq 1 60); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
    kill -KILL "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
  fi
  rm -f "$log"
}
trap stop_dockerd EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

for _ in $(seq 1 60); do
  docker info >/dev/null 2>&1 && break
  kill -0 "$pid" 2>/dev/null || { echo "with_dockerd.sh: dockerd exited:" >&2; tail -n 20 "$log" >&2; exit 1; }
  sleep 0.5
done
docker info >/dev/null 2>&1 || { echo "with_dockerd.sh: dockerd not up after 30 s:" >&2; tail -n 20 "$log" >&2; exit 1; }
echo "with_dockerd.sh: started dockerd (pid $pid) for: $*"
"$@"
