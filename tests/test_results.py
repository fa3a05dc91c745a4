"""json_safe: numpy arrays become plain lists, non-finite numbers become None (never NaN)."""

import json
import math

import numpy as np

from optimizer.results import json_safe


def test_arrays_finite_and_not():
    out = json_safe({"a": np.array([[1.0, 2.5], [3.0, -4.0]]), "b": np.array([1.0, np.nan]),
                     "c": np.array([np.inf, 2.0], dtype=np.float32), "d": np.arange(3),
                     "e": [np.float64(math.nan), (np.int64(2), np.bool_(True))]})
    assert out == {"a": [[1.0, 2.5], [3.0, -4.0]], "b": [1.0, None], "c": [None, 2.0],
                   "d": [0, 1, 2], "e": [None, [2, True]]}
    assert type(out["a"][0][0]) is float and type(out["d"][0]) is int
    json.dumps(out, allow_nan=False)  # strict JSON
