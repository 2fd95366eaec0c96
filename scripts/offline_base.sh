#!/usr/bin/env bash
# An offline base image for the Dockerfile, built from Debian's own packages, for machines that
# reach a Debian mirror but no image registry (air-gapped sites, CI here):
#
#   scripts/offline_base.sh                 # -> image tupa-base:bookworm (skipped if it exists)
#   scripts/offline_base.sh --force NAME    # rebuild, under another name
#   MIRROR=http://mirror.example/debian scripts/offline_base.sh
#   docker build --build-arg BASE=tupa-base:bookworm -t tupa .
#
# debootstrap --variant=minbase bookworm into a temporary directory (Python 3.11 with venv and
# pip from bookworm; nothing else but the essential packages), docs and apt's lists removed,
# then `tar | docker import`. The mirror is the machine's own (the first bookworm suite in
# /etc/apt/sources.list or /etc/apt/sources.list.d/*, security suites excluded) unless MIRROR
# says otherwise. Needs root (debootstrap), debootstrap and a running Docker daemon; about three
# minutes on two cores.
set -euo pipefail

NAME=tupa-base:bookworm
FORCE=0
while [ $# -gt 0 ]; do
  case "$1" in
    --force) FORCE=1 ;;
    -h | --help) sed -n '2,15p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    -*) echo "offline_base.sh: unknown option $1" >&2; exit 2 ;;
    *) NAME="$1" ;;
  esac
  shift
done

if [ "$FORCE" = 0 ] && docker image inspect "$NAME" >/dev/null 2>&1; then
  echo "offline_base.sh: $NAME exists (--force rebuilds it)"
  exit 0
fi
[ "$(id -u)" = 0 ] || { echo "offline_base.sh: debootstrap needs root" >&2; exit 2; }
command -v debootstrap >/dev/null || {
  echo "offline_base.sh: debootstrap is missing (apt-get install debootstrap)" >&2; exit 2; }

# The machine's Debian mirror: the URI of the first bookworm suite (one-line or deb822 format).
find_mirror() {
  local f
  for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
    [ -f "$f" ] || continue
    awk '$1 == "deb" { i = 2; if ($2 ~ /^\[/) { while ($i !~ /\]$/) i++; i++ }
                       if ($(i + 1) == "bookworm" && $i !~ /security/) { print $i; exit } }' "$f"
  done
  for f in /etc/apt/sources.list.d/*.sources; do
    [ -f "$f" ] || continue
    awk 'BEGIN { RS = ""; FS = "\n" }
         { uri = ""; suites = ""; enabled = 1
           for (i = 1; i <= NF; i++) {
             if ($i ~ /^URIs:/) { uri = $i; sub(/^URIs:[ \t]*/, "", uri); sub(/[ \t].*/, "", uri) }
             if ($i ~ /^Suites:/) suites = " " $i " "
             if ($i ~ /^Enabled:[ \t]*no/) enabled = 0 }
           if (enabled && suites ~ /[ \t]bookworm[ \t]/ && uri !~ /security/) { print uri; exit } }' "$f"
  done
}
MIRROR="${MIRROR:-$(find_mirror | head -n 1)}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"

ROOTFS="$(mktemp -d /tmp/tupa-base.XXXXXX)"
cleanup() {
  # debootstrap mounts /proc and /sys inside; unmount anything left before removing.
  grep -o " $ROOTFS/[^ ]*" /proc/mounts | sort -r | xargs -r -n 1 umount -l 2>/dev/null || true
  rm -rf --one-file-system "$ROOTFS"
}
trap cleanup EXIT

echo "offline_base.sh: debootstrap bookworm from $MIRROR into $ROOTFS"
start=$(date +%s)
debootstrap --variant=minbase --include=python3.11,python3.11-venv,python3-distutils \
  bookworm "$ROOTFS" "$MIRROR" >"$ROOTFS.log" 2>&1 || {
  tail -n 30 "$ROOTFS.log" >&2; rm -f "$ROOTFS.log"; exit 1; }
rm -f "$ROOTFS.log"

# Smaller: no package lists or caches, no manuals, docs (copyright files kept) or translations.
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/* "$ROOTFS"/var/log/* \
  "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/* "$ROOTFS"/usr/share/locale/*
find "$ROOTFS/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
printf 'Acquire::Languages "none";\n' >"$ROOTFS/etc/apt/apt.conf.d/90tupa-no-languages"
# The mirror for apt inside (the image itself needs none to run).
printf 'deb %s bookworm main\n' "$MIRROR" >"$ROOTFS/etc/apt/sources.list"

tar --numeric-owner -C "$ROOTFS" -c . | docker import \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' \
  --change 'CMD ["python3.11"]' \
  --message "debootstrap --variant=minbase bookworm $MIRROR + python3.11, python3.11-venv, python3-distutils" \
  - "$NAME" >/dev/null
echo "offline_base.sh: $NAME built in $(($(date +%s) - start)) s" \
  "($(docker image inspect -f '{{.Size}}' "$NAME" | awk '{printf "%.0f MB", $1 / 1e6}'))"
