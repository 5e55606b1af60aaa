#!/usr/bin/env bash
# The README's colour-by-label picture: a small synthetic set, a short training run, an open-vocabulary
# prediction written as a compressed PLY (SuperSplat) coloured by class, and `seggaussian render` of it.
# About 8 minutes on 2 cores (longer under load). Output: $OUT/labelled.compressed.ply (+ .legend.json/.png) and the PNG.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
OUT=${OUT:-out/colour-by}
PNG=${PNG:-docs/images/colour_by_semantic.png}
mkdir -p "$OUT"
$BIN/seggaussian synth --out "$OUT/raw" --scenes 4 --replica-scenes 1 --width 128 --views 12 --seed 0 --no-progress
$BIN/seggaussian build --source synthetic --root "$OUT/raw" --out "$OUT/dataset" --gaussians oracle \
    --oracle-gaussians 20000 --jobs 2 --no-progress | tail -n 1
$BIN/seggaussian split --data "$OUT/dataset" | tail -n 1
$BIN/ovgaussian train --data "$OUT/dataset" --out "$OUT/run" --epochs 16 --classes 20 --model-preset slim \
    --pixels-per-view 4096 --no-progress | tail -n 1
VAL=$($BIN/python -c "from seggaussian.shards import list_scenes; print(list_scenes('$OUT/dataset', 'val')[0])")
$BIN/seggaussian export-ply "$OUT/dataset" --scene "$VAL" --out "$OUT/scene.ply" | tail -n 1
$BIN/ovgaussian predict "$OUT/scene.ply" --run "$OUT/run" --vocab "wall, floor, ceiling, chair, table, sofa, bed, bookshelf, curtain" \
    --out "$OUT/labelled.compressed.ply" --color-by semantic | tail -n 1
$BIN/seggaussian render "$OUT/labelled.compressed.ply" --out "$PNG" --width 480 --height 360 --azimuth -60 --elevation 35
cp "$OUT/labelled.compressed.legend.png" "${PNG%.png}.legend.png"
# the same palette on the ground-truth labels of that scene, for comparison
$BIN/seggaussian export-ply "$OUT/dataset" --scene "$VAL" --out "$OUT/truth.ply" --color-by semantic | tail -n 1
$BIN/seggaussian render "$OUT/truth.ply" --out docs/images/colour_by_truth.png --width 480 --height 360 --azimuth -60 --elevation 35
