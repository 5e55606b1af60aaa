#!/usr/bin/env bash
# The README's colour-by-label picture, from what `make demo` leaves in $DEMO: the demo run's open-vocabulary
# prediction on the CPU-fitted splat of the val room (as users bring scenes), written as a compressed PLY
# (SuperSplat) coloured by class, and `seggaussian render` of it; the same palette on that splat's transferred
# ground-truth labels beside it. About a minute after `make demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
DEMO=${DEMO:-out/demo}
OUT=${OUT:-out/colour-by}
PNG=${PNG:-docs/images/colour_by_semantic.png}
[ -d "$DEMO/run" ] && [ -d "$DEMO/dataset" ] || { echo "$DEMO: no demo run or dataset (run make demo first)" >&2; exit 1; }
mkdir -p "$OUT"
VAL=$($BIN/python -c "from seggaussian.shards import list_scenes; print(list_scenes('$DEMO/dataset', 'val')[0])")
$BIN/seggaussian export-ply "$DEMO/dataset" --scene "$VAL" --out "$OUT/scene.ply" | tail -n 1
# the vocabulary in the order of the ScanNet++ top-100 list, so a class has the same colour in both pictures (the
# palette is indexed by vocabulary position in a prediction and by class id in the ground truth)
VOCAB="wall, ceiling, floor, table, door, ceiling lamp, cabinet, blinds, curtain, chair, storage cabinet, office chair, bookshelf, whiteboard, window, box, window frame, monitor, shelf, doorframe, pipe, heater, kitchen cabinet, sofa, windowsill, bed"
$BIN/ovgaussian predict "$OUT/scene.ply" --run "$DEMO/run" --vocab "$VOCAB" \
    --out "$OUT/labelled.compressed.ply" --color-by semantic | tail -n 1
$BIN/seggaussian render "$OUT/labelled.compressed.ply" --out "$PNG" --width 480 --height 360 --azimuth -60 --elevation 35
cp "$OUT/labelled.compressed.legend.png" "${PNG%.png}.legend.png"
$BIN/seggaussian export-ply "$DEMO/dataset" --scene "$VAL" --out "$OUT/truth.ply" --color-by semantic | tail -n 1
$BIN/seggaussian render "$OUT/truth.ply" --out docs/images/colour_by_truth.png --width 480 --height 360 --azimuth -60 --elevation 35
