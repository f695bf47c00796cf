"""User-facing JSON is valid JSON: a NaN or an infinity is written as null, never as a bare ``NaN``."""

import json
import math

import numpy as np
import pytest
import torch

from anm_torchrl.experiments.io import write_json, write_record
from anm_torchrl.strict_json import json_text, plain_json


def _strict_loads(text: str):
    """json.loads that refuses NaN / Infinity, as jq or JavaScript's JSON.parse do."""
    def refuse(name):
        raise ValueError(f"bare {name} in JSON")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_become_null_and_containers_plain():
    doc = {"nan": float("nan"), "inf": -math.inf, "tensor": torch.tensor([1.5, float("nan")]),
           "array": np.array([[1, 2]]), "scalar": np.float32(0.25), 3: (True, None)}
    assert _strict_loads(json_text(doc)) == {"nan": None, "inf": None, "tensor": [1.5, None], "array": [[1, 2]],
                                              "scalar": 0.25, "3": [True, None]}
    assert plain_json({"p": torch.tensor(2.0)}) == {"p": 2.0}


def test_json_text_keeps_dumps_options():
    assert json_text({"b": 1, "a": 2}, sort_keys=True, indent=1) == json.dumps({"a": 2, "b": 1}, indent=1)


@pytest.mark.parametrize("write", ["json", "record"])
def test_record_writers_never_write_bare_nan(tmp_path, write):
    rec = {"score": float("nan"), "curve": [1.0, float("inf")]}
    path = (write_json(tmp_path / "r.json", rec) if write == "json"
            else write_record(tmp_path, "r", rec, "table\n"))
    assert _strict_loads(path.read_text()) == {"score": None, "curve": [1.0, None]}
