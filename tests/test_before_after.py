"""``benchmarks/before_after.py``: the per-round pairing and its summary (no worker processes here)."""

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "before_after", Path(__file__).resolve().parents[1] / "benchmarks" / "before_after.py")
_mod = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_mod)
main, markdown_table, summarise = _mod.main, _mod.markdown_table, _mod.summarise


def _rec(tree, k, batch, rate, cpu):
    return {"tree": tree, "round": k, "batch": batch, "rate": rate, "cpu_per_transition": cpu}


def test_ratios_are_paired_per_round():
    # round 0 runs on a loaded machine (everything 4x slower): pairing by round keeps the ratio at 0.9 / 1.25
    recs = [_rec("before", 0, 1, 100.0, 4.0), _rec("after", 0, 1, 90.0, 3.2),
            _rec("before", 1, 1, 400.0, 1.0), _rec("after", 1, 1, 360.0, 0.8),
            _rec("before", 2, 1, 400.0, 1.0), _rec("after", 2, 1, 360.0, 0.8)]
    (row,) = summarise(recs, [1])
    assert row["rounds"] == 3
    assert row["ratio_wall"] == pytest.approx(0.9) and row["ratio_wall_min"] == pytest.approx(0.9)
    assert row["ratio_cpu"] == pytest.approx(1.25)  # CPU s per transition: before / after
    assert row["before_rate"] == 400.0 and row["after_rate"] == 360.0  # medians over rounds
    assert "| 1 | 400 | 360 | 0.90 [0.90, 0.90] | 1.25 [1.25, 1.25] |" in markdown_table([row])


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="--rounds"):
        main(["--rounds", "0"])
