"""rigctl.jsonable.jsonable: the one conversion of results to JSON values (calibration results,
the Allan results group, the Allan JSON export, batch summaries)."""
from __future__ import annotations

import json
import math

import numpy as np

from rigctl.jsonable import jsonable


def _sample() -> dict:
    return {"a": np.array([1.0, np.nan, np.inf]), "n": np.int64(3), "b": np.bool_(True),
            "x": np.float32(0.5), "t": (1, -np.inf), "s": np.str_("k"), "none": None,
            "_private": 1, 7: "int key", "nested": {"_unit": "deg/h", "v": [np.float64(2.0)]},
            "obj": complex(1, 2)}


def test_non_finite_become_null_and_the_result_is_strict_json() -> None:
    out = jsonable(_sample())
    text = json.dumps(out, allow_nan=False)  # raises if a NaN or inf were left
    back = json.loads(text)
    assert back["a"] == [1.0, None, None]
    assert back["t"] == [1, None]
    assert back["n"] == 3 and type(out["n"]) is int
    assert back["b"] is True and type(out["b"]) is bool
    assert back["x"] == 0.5 and back["s"] == "k" and back["none"] is None
    assert "_private" not in back and back["nested"] == {"v": [2.0]}
    assert back["7"] == "int key"
    assert back["obj"] == "(1+2j)"


def test_keep_nonfinite_keeps_nan_and_inf() -> None:
    out = jsonable(_sample(), keep_nonfinite=True)
    a = out["a"]
    assert a[0] == 1.0 and math.isnan(a[1]) and a[2] == math.inf
    assert out["t"] == [1, -math.inf]
    assert "_private" not in out and out["nested"] == {"v": [2.0]}
    back = json.loads(json.dumps(out))  # Python's json round-trips NaN / Infinity
    assert math.isnan(back["a"][1]) and back["a"][2] == math.inf
