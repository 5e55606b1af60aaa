"""Axis-letter frames: three letters naming where a frame's x, y, z axes point, converted to the toolkit's RDF.

One letter per axis, one from each pair R/L (right/left), U/D (up/down), F/B (forward/backward), in any order:
``RDF`` is OpenCV/COLMAP (the toolkit's world convention), ``RUB`` OpenGL/three.js/nerfstudio cameras, ``RUF``
Unity (left-handed), ``FLU`` ROS, ``RFU`` a z-up right-handed world, ``LUF``... The letters name directions of
the *scene's* frame: R = +x, D = +y, F = +z of the scene, whatever the scene's own up direction is.

``axes_to_rdf(code)`` is the matrix that maps coordinates expressed in the coded frame to RDF coordinates: its
column ``i`` is the RDF unit vector of letter ``i`` (``RUB -> diag(1, -1, -1)``). An odd number of flipped or
swapped axes gives a reflection (det -1), e.g. ``RUF``.
"""

from __future__ import annotations

import numpy as np

#: RDF unit vector of each axis letter.
AXIS_VECTORS = {
    "R": (1.0, 0.0, 0.0), "L": (-1.0, 0.0, 0.0),
    "D": (0.0, 1.0, 0.0), "U": (0.0, -1.0, 0.0),
    "F": (0.0, 0.0, 1.0), "B": (0.0, 0.0, -1.0),
}
#: The three letter pairs; a code takes exactly one letter of each.
AXIS_PAIRS = ("RL", "UD", "FB")


def parse_axes_code(code: str) -> str:
    """``code`` upper-cased if it is a valid three-letter axes code; ValueError (one line) otherwise."""
    hint = "expected three letters, one from each of R/L, U/D, F/B in any order (e.g. RDF, RUB, FLU)"
    if not isinstance(code, str):
        raise ValueError(f"axes code {code!r}: {hint}")
    letters = code.strip().upper()
    if len(letters) != 3 or any(letter not in AXIS_VECTORS for letter in letters):
        raise ValueError(f"axes code {code!r}: {hint}")
    for pair in AXIS_PAIRS:
        if sum(letter in pair for letter in letters) != 1:
            raise ValueError(f"axes code {code!r}: needs exactly one of {pair[0]}/{pair[1]}; {hint}")
    return letters


def axes_to_rdf(code: str) -> np.ndarray:
    """``[3, 3]`` float64 signed permutation taking coordinates in the ``code`` frame to RDF coordinates."""
    letters = parse_axes_code(code)
    return np.array([AXIS_VECTORS[letter] for letter in letters], dtype=np.float64).T
