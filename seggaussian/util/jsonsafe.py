"""JSON-ready values: every report and metrics file goes through ``json_safe`` before ``json.dump``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: NaN policies of JSON output. ``null``: NaN/Inf floats become null (reports: an undefined metric is
#: missing, not a number). ``error``: a NaN/Inf anywhere refuses the whole payload (state that must read
#: back exactly, e.g. a training checkpoint), before anything is written.
NAN_AS_NULL = "null"
NAN_IS_ERROR = "error"
NAN_POLICIES = (NAN_AS_NULL, NAN_IS_ERROR)


def json_safe(value, nan: str = NAN_AS_NULL, where: str = "payload"):
    """``value`` with numpy scalars/arrays as Python numbers/lists, paths as strings, tuples as lists, dict
    keys as strings, and NaN/Inf floats as None (JSON has no NaN; a report never writes one).

    ``nan``: one of NAN_POLICIES; with ``error``, a NaN/Inf raises ValueError naming its place (``where``)."""
    if nan not in NAN_POLICIES:
        raise ValueError(f"NaN policy must be one of {NAN_POLICIES}, got {nan!r}")
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        value = value.item()
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        if nan == NAN_IS_ERROR:
            raise ValueError(f"{where} holds {value} (JSON has no NaN/Inf; refused)")
        return None
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist(), nan, where)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {str(k): json_safe(v, nan, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, nan, f"{where}[{i}]") for i, v in enumerate(value)]
    return value
