#!/usr/bin/env bash
# What the container test needs on a Debian machine, installed with apt-get when missing (root):
# the Docker daemon and client (docker.io), debootstrap (scripts/offline_base.sh), and the
# Compose v2 plugin (`docker compose`). Bookworm's own docker-compose is Compose v1 (no
# `docker compose`, no inline configs), so on bookworm the plugin comes from Debian trixie's
# docker-compose package (a static binary; libc6 >= 2.34), fetched with apt-get through a
# private package list (the machine's sources are left as they are) and installed with apt-get.
# Does nothing when everything is there.
set -euo pipefail

missing=()
command -v dockerd >/dev/null || missing+=(docker.io)
command -v docker >/dev/null || missing+=(docker.io)
command -v debootstrap >/dev/null || missing+=(debootstrap)
compose_ok=1
docker compose version >/dev/null 2>&1 || compose_ok=0
if [ ${#missing[@]} = 0 ] && [ "$compose_ok" = 1 ]; then
  exit 0
fi
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then
  echo "install_docker.sh: missing ${missing[*]:-} $([ "$compose_ok" = 1 ] || echo 'docker compose')" \
    "and not root on Debian: install them (Docker Engine with the Compose plugin, debootstrap)" >&2
  exit 1
fi
export DEBIAN_FRONTEND=noninteractive NEEDRESTART_SUSPEND=1
apt-get update -qq
if [ ${#missing[@]} != 0 ]; then
  mapfile -t packages < <(printf '%s\n' "${missing[@]}" | sort -u)
  apt-get install -y -qq "${packages[@]}" >/dev/null
fi
if docker compose version >/dev/null 2>&1; then
  exit 0
fi

# Compose v2: this release's docker-compose when it is v2 (trixie and later), else trixie's.
candidate="$(apt-cache policy docker-compose | awk '/Candidate:/ { print $2 }')"
if [ -n "$candidate" ] && [ "${candidate%%.*}" -ge 2 ] 2>/dev/null; then
  apt-get install -y -qq docker-compose >/dev/null
else
  work="$(mktemp -d)"
  trap 'rm -rf "$work"' EXIT
  mkdir -p "$work/lists/partial" "$work/cache/archives/partial"
  echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] http://deb.debian.org/debian trixie main" \
    >"$work/sources.list"
  opts=(-o "Dir::Etc::SourceList=$work/sources.list" -o Dir::Etc::SourceParts=/dev/null
    -o "Dir::State::Lists=$work/lists" -o "Dir::Cache=$work/cache" -o APT::Sandbox::User=root)
  apt-get "${opts[@]}" update -qq
  (cd "$work" && apt-get "${opts[@]}" download docker-compose >/dev/null)
  apt-get install -y -qq "$work"/docker-compose_*.deb >/dev/null
fi
docker compose version
