"""Axis-letter frames -> RDF matrices; bad codes refused."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from seggaussian.frames.axes import axes_to_rdf


def test_known_frames():
    np.testing.assert_array_equal(axes_to_rdf("RDF"), np.eye(3))
    np.testing.assert_array_equal(axes_to_rdf("RUB"), np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_array_equal(axes_to_rdf("rub"), np.diag([1.0, -1.0, -1.0]))
    # ROS (x forward, y left, z up): a point 1 m ahead is RDF z = 1, 1 m left is RDF x = -1, 1 m up is RDF y = -1
    flu = axes_to_rdf("FLU")
    np.testing.assert_array_equal(flu @ [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(flu @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0])
    np.testing.assert_array_equal(flu @ [0.0, 0.0, 1.0], [0.0, -1.0, 0.0])
    # a z-up right-handed world (x right, y forward, z up)
    np.testing.assert_array_equal(axes_to_rdf("RFU") @ [0.0, 0.0, 2.0], [0.0, -2.0, 0.0])


def test_handedness():
    for code in ("RDF", "RUB", "FLU", "RFU", "LUF"):
        assert np.linalg.det(axes_to_rdf(code)) == pytest.approx(1.0), code
    for code in ("RUF", "LDF", "RDB", "FRU"):
        assert np.linalg.det(axes_to_rdf(code)) == pytest.approx(-1.0), code


def test_all_48_codes_are_signed_permutations_and_distinct():
    seen = set()
    for order in itertools.permutations(("RL", "UD", "FB")):
        for letters in itertools.product(*order):
            m = axes_to_rdf("".join(letters))
            np.testing.assert_array_equal(m.T @ m, np.eye(3))
            assert set(np.abs(m).sum(axis=0)) == {1.0}
            seen.add(m.tobytes())
    assert len(seen) == 48


def test_inverse_frame_maps_back():
    m = axes_to_rdf("FLU")
    point_rdf = np.array([0.3, -1.0, 2.0])
    np.testing.assert_allclose(m @ (m.T @ point_rdf), point_rdf)


@pytest.mark.parametrize("code", ["", "RD", "RDFX", "RRF", "RLF", "UDR", "XYZ", "R D", "RDF!", None, 3])
def test_bad_codes_are_refused_in_one_line(code):
    with pytest.raises(ValueError, match="axes code") as info:
        axes_to_rdf(code)
    assert "\n" not in str(info.value)
