#!/usr/bin/env bash
# Build the wheel, install it into a fresh virtual environment outside the checkout, and run commands
# that read the package data (class lists, the Replica mapping) from there: a source-tree path would fail.
# Usage: bash scripts/check_wheel.sh [PYTHON]   (PYTHON defaults to python3; torch comes from the local CPU build)
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
py=${1:-python3}
work=$(mktemp -d "${TMPDIR:-/tmp}/seggaussian-wheel.XXXXXX")
trap 'rm -rf "$work"' EXIT

"$repo/.venv/bin/python" -m pip wheel -q --no-deps --no-build-isolation "$repo" -w "$work/dist"
wheel=$(ls "$work"/dist/seggaussian-*.whl)
"$py" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q --upgrade pip
"$work/venv/bin/python" -m pip install -q torch==2.13.0
"$work/venv/bin/python" -m pip install -q "$wheel"

cd "$work"   # nothing of the checkout on sys.path from here on
"$work/venv/bin/python" - <<'PY'
import seggaussian.core.constants as c, seggaussian.core.classes as k
assert "site-packages" in str(c.DATA_SPECS_DIR), c.DATA_SPECS_DIR
assert len(k.class_names()) == 100 and k.class_names()[0] == "wall"
print("package data from", c.DATA_SPECS_DIR)
PY
ply="$repo/../shared/realdata/loadersgl_train-1000.ply"
if [ ! -f "$ply" ]; then
  echo "no real PLY at $ply: inspecting a PLY written by the installed package instead"
  ply="$work/written.ply"
  "$work/venv/bin/python" - "$ply" <<'PY'
import sys, numpy as np
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.writer import write_gaussians_ply
rng = np.random.default_rng(0)
n = 100
f = lambda *s: rng.normal(size=s).astype(np.float32)
write_gaussians_ply(sys.argv[1], Gaussians(f(n, 3), f(n, 4), f(n, 3) - 4, f(n), f(n, 16, 3)))
PY
fi
"$work/venv/bin/seggaussian" inspect "$ply"
"$work/venv/bin/seggaussian" synth --out "$work/raw" --layout scannetpp --scenes 1 --views 2 --width 64 --no-progress
echo "wheel check: OK ($(basename "$wheel"))"
