#!/usr/bin/env bash
# The whole mst chain on the bundled sample (run by `make demo`; mst must be on PATH).
#   synth (only when the sequence is absent) -> convert-model -> init -> track -> fuse -> c2m -> eval traj -> report
# Every stage reads the previous stage's files; results land in $OUT (default demo-out/).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
OUT=${OUT:-demo-out}
SEQ=$OUT/seq
mkdir -p "$OUT"

step() { printf '\n\033[1m== %s\033[0m\n' "$*" >&2; }

# run [">" FILE] CMD...: append the exact command line (shell-quoted, with its stdout file) to $LOG, then
# run it. $OUT/commands.sh is the run log that `mst report` shows with each stage's --json "config".
LOG=$OUT/commands.sh
: > "$LOG"
run() {
  local out=""
  if [ "$1" = ">" ]; then out=$2; shift 2; fi
  { printf "%q" "$1"; for a in "${@:2}"; do printf " %q" "$a"; done
    if [ -n "$out" ]; then printf ' > %q' "$out"; fi; echo; } >> "$LOG"
  if [ -n "$out" ]; then "$@" > "$out"; else "$@"; fi
}

step "synth: 60-frame RGB-D orbit of the sample house, ground truth included (skipped when present)"
run bash "$HERE/make_sample.sh" "$SEQ"

step "convert-model: TIN -> polygon model"
run ">" "$OUT/convert-model.json" mst convert-model "$HERE/building_tin.obj" -o "$OUT/building.wrl" --json

step "init: first pose from the frame-0 clicks"
run ">" "$OUT/init.json" mst init --model "$OUT/building.wrl" --camera "$SEQ/camera.json" --clicks "$SEQ/clicks.txt" \
  -o "$OUT/pose0.txt" --json

step "track: model-based edges + RGB-D SLAM"
run ">" "$OUT/track.json" mst track "$SEQ/rgb" --fps 30 --model "$OUT/building.wrl" --camera "$SEQ/camera.json" \
  --init "$OUT/pose0.txt" --depth "$SEQ/depth" -o "$OUT/traj.txt" --json

step "fuse: depth frames -> cloud in model coordinates"
run ">" "$OUT/fuse.json" mst fuse --traj "$OUT/traj.txt" --fps 30 --depth "$SEQ/depth" --camera "$SEQ/camera.json" \
  --voxel 0.02 -o "$OUT/cloud.ply" --json

step "c2m: fused cloud vs the rendered scene (Table 1)"
run ">" "$OUT/c2m.json" mst c2m "$OUT/cloud.ply" "$SEQ/scene.ply" --thresholds 0.01,0.02,0.05,0.1 --markdown "$OUT/c2m.md" --json

step "eval traj: tracked trajectory vs ground truth"
run ">" "$OUT/eval.json" mst eval traj "$OUT/traj.txt" "$SEQ/gt.txt" --align none --json

step "report: one self-contained HTML page of the run (open it in a browser)"
run mst report "$OUT" -o "$OUT/report.html" --frames "$SEQ/rgb" --model "$OUT/building.wrl" --camera "$SEQ/camera.json" --fps 30

# ---- the headline case (issue 11): a UAV survey of a procedural city block, in OUT/uav/
UAV=$OUT/uav
mkdir -p "$UAV"
LOG=$UAV/commands.sh  # the UAV run's own log
: > "$LOG"
step "uav: a procedural LoD2-like city block (36 buildings, flat and gabled roofs)"
run python -m mst.meshtools.generate city_block --polygons --buildings 36 -o "$UAV/city.wrl"

step "uav synth: 8 s survey pass 60 m up, camera 45 deg down, hovering while it looks away from the block"
run mst synth uav --model "$UAV/city.wrl" -o "$UAV/seq" --frames 240 --width 320 --height 240 --no-depth \
  --model-texture --aa 4 --texture-size 512 --overwrite -q

step "uav convert-model + init + track (default mode) + eval"
run mst convert-model "$UAV/seq/model.obj" -o "$UAV/city_from_tin.wrl" -q
run mst init --model "$UAV/city_from_tin.wrl" --camera "$UAV/seq/camera.json" --clicks "$UAV/seq/clicks.txt" -o "$UAV/pose0.txt" -q
run ">" "$UAV/track.json" mst track "$UAV/seq/rgb" --fps 30 --model "$UAV/city_from_tin.wrl" --camera "$UAV/seq/camera.json" \
  --init "$UAV/pose0.txt" -o "$UAV/traj.txt" --json
run ">" "$UAV/eval.json" mst eval traj "$UAV/traj.txt" "$UAV/seq/gt.txt" --align none --json

printf '\nDemo outputs in %s/ (report: %s/report.html)\n' "$OUT" "$OUT" >&2
