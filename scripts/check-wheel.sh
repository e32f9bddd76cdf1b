#!/bin/sh
# What a user gets from `pip install fleetslam[cloud]`, checked end to end: build the sdist
# and the wheel as `python -m build` does (the wheel from the sdist, so a file the sdist
# leaves out is missed here too), install the wheel into a fresh venv outside the checkout,
# and run `fleetslam demo --in-process` from another directory.
#
#   sh scripts/check-wheel.sh [WORK_DIR]      (default: a new temporary folder)
#
# A few minutes with pip's cache warm (most of it installing the cloud extra), too slow for
# the test suite: tests/test_packaging.py checks the built wheel's contents and imports it
# from another directory in seconds. FRAMES (default 40) sets the demo's frames per robot.
set -eu
PYTHON="${PYTHON:-python3}"
FRAMES="${FRAMES:-40}"
ROOT=$(cd "$(dirname "$0")/.." && pwd)
WORK="${1:-$(mktemp -d)}"
mkdir -p "$WORK"
WORK=$(cd "$WORK" && pwd)
case "$WORK/" in "$ROOT"/*) echo "check-wheel: $WORK is inside the checkout $ROOT" >&2; exit 2;; esac

# A copy: building writes build/ and *.egg-info beside the sources.
rm -rf "$WORK/project" "$WORK/dist" "$WORK/venv" "$WORK/elsewhere"
mkdir -p "$WORK/project" "$WORK/elsewhere"
cp "$ROOT/pyproject.toml" "$ROOT/README.md" "$WORK/project/"
cp -R "$ROOT/src" "$WORK/project/src"
find "$WORK/project" -name __pycache__ -prune -exec rm -rf {} + -o -name '*.egg-info' -prune -exec rm -rf {} +

"$PYTHON" -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install --quiet build
"$WORK/venv/bin/python" -m build --outdir "$WORK/dist" "$WORK/project"
WHEEL=$(ls "$WORK"/dist/fleetslam-*.whl)
"$WORK/venv/bin/python" -m pip install --quiet "$WHEEL[cloud]"

cd "$WORK/elsewhere"
"$WORK/venv/bin/python" -m fleetslam --help >/dev/null
"$WORK/venv/bin/fleetslam" demo --in-process --frames "$FRAMES" --out run
test -f run/summary.json && test -f run/report/report.html
echo "check-wheel: OK ($WHEEL installed in $WORK/venv; demo in $WORK/elsewhere/run)"
