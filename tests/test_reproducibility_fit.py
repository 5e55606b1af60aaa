"""A fit freshly compiled and one from the numba cache write the same PLY (tests/repro_runs.py)."""

from __future__ import annotations

from repro_runs import numba_cache_files, run_driver


def test_fit_cold_and_warm_numba_cache_write_identical_ply(tmp_path):
    from seggaussian.sources.synthetic import generate as synthetic
    raw = tmp_path / "raw"
    (scene_id,) = synthetic.synthesize(raw / "scannetpp", 1, 0, "scannetpp",
                                       synthetic.SynthConfig(width=48, num_views=9, max_edge=0.25))
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    cold = run_driver(cache, "fit", str(raw), scene_id, str(tmp_path / "cold.ply"))
    assert numba_cache_files(cache) > 0
    warm = run_driver(cache, "fit", str(raw), scene_id, str(tmp_path / "warm.ply"))
    assert cold == warm
