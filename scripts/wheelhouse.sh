#!/usr/bin/env bash
# The wheels an offline image build installs (docker build --build-arg OFFLINE=1): torch==2.13.0
# (CPU) and every dependency in pyproject.toml, plus what building the package needs
# (setuptools), downloaded with this machine's pip (its index, its find-links, its certificates)
# into build/wheels, which the Dockerfile copies into its build stage only.
#
#   scripts/wheelhouse.sh [DIR]      # default build/wheels; nothing to do when it is up to date
#
# PYTHON (default python3.11, or .venv/bin/python when present) runs pip: the wheels must suit
# CPython 3.11 on x86-64 glibc Linux, as in the image. Only wheels (--only-binary :all:): the
# image has no compiler. The optional extras (ns3, ray, dev) are left out. With .venv, the
# versions are those installed there (pip freeze as constraints), so that the image runs what
# make test tested.
set -euo pipefail
cd "$(dirname "$0")/.."

DIR="${1:-build/wheels}"
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3.11; fi
fi

mkdir -p "$DIR"
REQS="$DIR/requirements.txt"
# torch pinned as in the Makefile; the rest as pyproject.toml says; the build backend.
"$PYTHON" - "$REQS.new" <<'EOF'
import sys
import tomllib

with open("pyproject.toml", "rb") as f:
    project = tomllib.load(f)
lines = ["torch==2.13.0", *project["project"]["dependencies"]]
lines += project["build-system"]["requires"]
with open(sys.argv[1], "w") as out:
    out.write("\n".join(lines) + "\n")
EOF

if [ "$PYTHON" = .venv/bin/python ]; then
  # pip freeze's pins, less the project itself (editable) and what is not a plain pin.
  "$PYTHON" -m pip freeze --exclude-editable 2>/dev/null | grep -E '^[A-Za-z0-9_.-]+==' \
    | grep -v -i '^tupa==' >"$DIR/constraints.txt.new" || true
  printf -- '-c constraints.txt\n' >>"$REQS.new"
else
  : >"$DIR/constraints.txt.new"
fi

if [ -f "$DIR/.complete" ] && cmp -s "$REQS.new" "$REQS" \
  && cmp -s "$DIR/constraints.txt.new" "$DIR/constraints.txt"; then
  rm -f "$DIR/constraints.txt.new"
  rm -f "$REQS.new"
  echo "wheelhouse.sh: $DIR is up to date ($(find "$DIR" -name '*.whl' | wc -l) wheels)"
  exit 0
fi
mv "$REQS.new" "$REQS"
mv "$DIR/constraints.txt.new" "$DIR/constraints.txt"
rm -f "$DIR/.complete" "$DIR"/*.whl  # afresh: no stale versions left for the image to pick
start=$(date +%s)
# (pip's warnings about find-links locations this machine's configuration names but lacks: noise)
"$PYTHON" -m pip download --quiet --only-binary :all: --dest "$DIR" -r "$REQS" \
  2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
touch "$DIR/.complete"
echo "wheelhouse.sh: $(find "$DIR" -name '*.whl' | wc -l) wheels in $DIR" \
  "($(du -sm "$DIR" | cut -f1) MB, $(($(date +%s) - start)) s)"
