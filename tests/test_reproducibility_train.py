"""A training run freshly compiled and one from the numba cache give the same bytes (tests/repro_runs.py)."""

from __future__ import annotations

from repro_runs import numba_cache_files, run_driver


def test_training_cold_and_warm_numba_cache_hash_equal(tmp_path):
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    cold = run_driver(cache, "train", str(tmp_path / "cold"))
    assert numba_cache_files(cache) > 0  # the first run compiled (and stored) its kernels
    warm = run_driver(cache, "train", str(tmp_path / "warm"))
    assert cold == warm
