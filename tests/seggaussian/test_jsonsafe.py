import json
import math
from pathlib import Path

import numpy as np

from seggaussian.util.jsonsafe import json_safe


def test_json_safe_converts_numpy_paths_and_non_finite_values():
    payload = {"f": np.float32(0.25), "i": np.int64(3), "nan": math.nan, "inf": np.float64(np.inf),
               "arr": np.array([[1.0, np.nan]]), "path": Path("a/b"), 7: (True, np.bool_(False))}
    out = json_safe(payload)
    assert out == {"f": 0.25, "i": 3, "nan": None, "inf": None, "arr": [[1.0, None]], "path": "a/b",
                   "7": [True, False]}
    json.dumps(out, allow_nan=False)  # strict JSON
