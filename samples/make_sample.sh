#!/usr/bin/env bash
# Render the bundled sample sequence: a 60-frame RGB-D orbit (640x480, 30 fps) of the small gabled
# house samples/building_tin.obj, with ground truth, into DIR (default: ${OUT:-demo-out}/seq).
# Skips the work when DIR already holds a finished sequence (DIR/scene.json).
# Usage: samples/make_sample.sh [DIR]      (needs `mst` on PATH, e.g. PATH=.venv/bin:$PATH)
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
DIR="${1:-${OUT:-demo-out}/seq}"
if [ -f "$DIR/scene.json" ]; then
    echo "sample sequence already in $DIR" >&2
    exit 0
fi
mkdir -p "$(dirname "$DIR")"
mst synth orbit --model "$HERE/building_tin.obj" -o "$DIR" --frames 60 --depth --video --click-noise 1.0 --seed 0
