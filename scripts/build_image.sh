#!/usr/bin/env bash
# The image, built where no image registry (and no PyPI) is reachable from the build: the base
# from Debian's packages (scripts/offline_base.sh, once), the wheels from this machine's pip
# (scripts/wheelhouse.sh, again only when the dependencies change), then docker build with
# OFFLINE=1 (no network inside the build). Layers are cached: after a code change only the
# package's own layers are rebuilt.
#
#   scripts/build_image.sh                                  # -> image tupa
#   TUPA_IMAGE=tupa:dev scripts/build_image.sh              # another tag
#   TUPA_BASE=python:3.11-slim scripts/build_image.sh       # another base (pulled), same wheels
#
# Then: TUPA_API_TOKEN=... docker compose up -d (the compose file's image is tupa).
set -euo pipefail
cd "$(dirname "$0")/.."

IMAGE="${TUPA_IMAGE:-tupa}"
BASE="${TUPA_BASE:-tupa-base:bookworm}"

if [ "$BASE" = tupa-base:bookworm ]; then
  scripts/offline_base.sh "$BASE"
fi
scripts/wheelhouse.sh build/wheels
start=$(date +%s)
docker build --build-arg BASE="$BASE" --build-arg OFFLINE=1 -t "$IMAGE" .
echo "build_image.sh: $IMAGE built in $(($(date +%s) - start)) s from $BASE" \
  "($(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.0f MB", $1 / 1e6}'))"
