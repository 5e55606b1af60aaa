"""The stress generators with a small N: no NaN/Inf anywhere, every malformed input ends in a clean error
or a counted repair."""

import numpy as np
import pytest

from ovgaussian.train.stress_losses import LOSS_FAMILY
from seggaussian.tools import stress


@pytest.fixture(scope="module")
def report():
    return stress.run_stress(stress.StressConfig(cases=12, seed=3), families=(*stress.DATASET_FAMILIES, LOSS_FAMILY))


def test_no_nan_inf_and_no_crash(report):
    assert report.failures == [], [c._asdict() for c in report.failures]
    assert report.nan_inf_found == 0 and report.crashes == 0
    assert report.cases_tried == 12 * 5


def test_malformed_inputs_end_in_clean_errors_or_repairs(report):
    broken = report.by_family["broken_file"]
    assert broken == {"clean_error": 12}
    ply = report.by_family["ply"]
    # corruptions that need fixing are repaired and counted; benign extremes (non-unit quaternions,
    # duplicate positions, far offsets, denormal scales) pass untouched
    assert ply.get("repaired", 0) >= 6
    assert set(ply) <= {"ok", "repaired", "clean_error"}


def test_classify_separates_own_errors_from_dependency_errors():
    def own():
        raise ValueError("file.ply: property 'opacity' missing")

    assert stress.classify("x", "own", own).outcome == "crash"  # raised in tests/, not in the package
    assert stress.classify("x", "nan", lambda: stress.require_finite("t", np.array([np.nan]))).outcome == "nan_inf"
    assert stress.classify("x", "ok", lambda: None).outcome == "ok"
    assert stress.classify("x", "fix", lambda: "clamped 3").outcome == "repaired"

    def dependency():
        np.zeros(3).reshape(7)

    assert stress.classify("x", "dep", dependency).outcome == "crash"

    def package_error():
        from seggaussian.core.gaussians import sh_degree_from_coeffs

        sh_degree_from_coeffs(7)

    assert stress.classify("x", "pkg", package_error).outcome == "clean_error"


def test_far_offset_rendering_is_invariant():
    rng = np.random.default_rng(0)
    g = stress.random_gaussians(rng, 50)
    stress.check_far_offset(g, stress.camera_facing(np.zeros(3)), "auto")


def test_every_corruption_changes_the_input():
    rng = np.random.default_rng(1)
    base = stress.random_gaussians(rng, 40)
    for kind in stress.CORRUPTIONS:
        out = stress.corrupt(base, kind, np.random.default_rng(2))
        changed = any(not np.array_equal(getattr(out, f), getattr(base, f), equal_nan=True)
                      for f in ("means", "quats", "log_scales", "opacity_logits", "sh"))
        assert changed, kind
