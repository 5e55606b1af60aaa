#!/usr/bin/env bash
# The README's main job on the embedded synthetic data. Grows with the pipeline.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
OUT=${OUT:-out/demo}
mkdir -p "$OUT"
$BIN/seggaussian --version
