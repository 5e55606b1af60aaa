#!/usr/bin/env bash
# GPU checks, run on a lent GPU machine (the project's CI has none): the CUDA-marked tests and the paper-scale
# training step with the network and the losses on the GPU (bench_paper_step.py --device cuda), once per
# devoxelization named in $DEVOXELIZE (default "nearest"; e.g. DEVOXELIZE="nearest trilinear"); then the step
# without loader workers against with N, in one run, for each N in $WORKERS (default "1 2"; empty: none).
#
#   bash benchmarks/device_check.sh [SOURCE_DIR]     # results under $OUT (default /tmp/device-check)
#
# The machine's own python3 must hold torch with CUDA, numba, pyarrow, scipy, safetensors, click and pytest; the
# other dependencies (plyfile, trimesh, zstandard, deflate) can come as wheels in $WHEELS (default .whl), which
# are installed into /tmp/site first. SOURCE_DIR (default: this checkout) is the tree whose code runs.
set -uo pipefail
OUT=${OUT:-/tmp/device-check}
mkdir -p "$OUT"
WHEELS=$(realpath "${WHEELS:-.whl}" 2>/dev/null || true)
cd "${1:-.}" || exit 2
if [ -n "$WHEELS" ] && ls "$WHEELS"/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
      "$WHEELS"/*.whl || exit 2
  export PYTHONPATH=/tmp/site
fi
# seggaussian.data_specs is the folder data_specs/ (pyproject's package-dir): without an install, link it in place
if [ ! -e seggaussian/data_specs ]; then
  ln -s ../data_specs seggaussian/data_specs && trap 'rm -f seggaussian/data_specs' EXIT  # leave no file behind
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  nproc
  python3 -c "import torch, numba, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda,
torch.cuda.is_available(), 'numba', numba.__version__, 'numpy', numpy.__version__)"; } 2>&1 | tee "$OUT/machine.txt"
echo "== CUDA tests"
timeout "${TEST_TIMEOUT:-240}" python3 -m pytest -q -p no:cacheprovider -m cuda -rs \
    tests/ovgaussian/test_train.py tests/ovgaussian/test_train_loader.py tests/ovgaussian/test_ensemble.py \
    tests/seggaussian/render/test_pixel_blend.py \
    > "$OUT/pytest_cuda.log" 2>&1
echo "pytest exit $?"; tail -n 12 "$OUT/pytest_cuda.log"
[ "${STEPS:-3}" = 0 ] && exit 0  # STEPS=0: the tests alone
for devoxelize in ${DEVOXELIZE:-nearest}; do
  echo "== paper-scale step on the GPU ($devoxelize devoxelization)"
  timeout "${STEP_TIMEOUT:-300}" python3 benchmarks/bench_paper_step.py --device cuda --steps "${STEPS:-3}" \
      --devoxelize "$devoxelize" --max-peak-gb 128 > "$OUT/paper_step_cuda_$devoxelize.txt" 2>&1
  echo "bench exit $?"; tail -n 8 "$OUT/paper_step_cuda_$devoxelize.txt"
done
for workers in ${WORKERS-1 2}; do
  echo "== paper-scale step on the GPU without and with $workers loader workers"
  timeout "${STEP_TIMEOUT:-300}" python3 benchmarks/bench_paper_step.py --device cuda --steps "${STEPS:-3}" \
      --compare-workers "$workers" --max-peak-gb 128 > "$OUT/paper_step_cuda_workers$workers.txt" 2>&1
  echo "bench exit $?"; tail -n 9 "$OUT/paper_step_cuda_workers$workers.txt"
done
