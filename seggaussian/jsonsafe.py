"""JSON-ready values: every report and metrics file goes through ``json_safe`` before ``json.dump``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def json_safe(value):
    """``value`` with numpy scalars/arrays as Python numbers/lists, paths as strings, tuples as lists, dict
    keys as strings, and NaN/Inf floats as None (JSON has no NaN; a report never writes one)."""
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value
