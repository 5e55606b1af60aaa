"""Helpers of the bitwise reproducibility tests (issue 16; test_reproducibility_train.py and _fit.py, two files
so that the two slowest tests run in two pytest-xdist workers).

The claim: one seed, one machine, one thread count -> the same bytes.

Every numba kernel is run both freshly compiled (an empty ``NUMBA_CACHE_DIR``, as on a fresh checkout) and
loaded from the cache: with ``reassoc`` in the rasterizer's fast-math flags those two gave different gradients
(a fit of 89,746 vs 89,778 Gaussians). Each run is its own process (tests/repro_driver.py), so the in-process
dispatcher cache cannot hide a difference. Resumed == uninterrupted, bit for bit (weights, buffers, momentum,
metrics): tests/test_train.py::test_training_decreases_loss_and_resume_continues_the_same_curve.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DRIVER = REPO / "tests" / "repro_driver.py"
#: Two threads for numba and torch in every run: the claim is per machine and thread count.
THREADS = "2"


def run_driver(cache: Path, *args: str) -> str:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), NUMBA_NUM_THREADS=THREADS, OMP_NUM_THREADS=THREADS,
               MKL_NUM_THREADS=THREADS)
    done = subprocess.run([sys.executable, str(DRIVER), *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip().splitlines()[-1]


def numba_cache_files(cache: Path) -> int:
    return sum(1 for _ in cache.rglob("*.nbc"))
