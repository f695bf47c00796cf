"""The committed parity record ``results/parity/parity.json`` (``python -m anm_torchrl.benchmarks.parity``).

The README's "Correctness against gym-anm" figures come from it: every fixture must pass on every backend with
the parity tests' tolerances (states 1e-6 MW / MVAr / MWh, rewards 1e-6 relative, identical terminations), or
be QP-inexact (rare rows where gym-anm's default cvxpy projection was off and gym-anm replayed with accurate
projections equals this package),
and the record must cover exactly the fixture files present (a new or removed fixture means: re-run it).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from anm_torchrl.benchmarks.parity import BACKENDS, REWARD_RTOL, STATE_TOL, fixture_names

RECORD = Path(__file__).resolve().parents[1] / "results" / "parity" / "parity.json"


@pytest.fixture(scope="module")
def record() -> dict:
    return json.loads(RECORD.read_text())


def test_record_covers_the_fixtures_present(record):
    names = fixture_names()
    assert len(names) >= 5  # ANM6-Easy and the four generic networks are committed
    assert sorted(record["fixtures"]) == sorted(names), "fixtures changed: re-run anm_torchrl.benchmarks.parity"
    for name, per_backend in record["fixtures"].items():
        assert sorted(per_backend) == sorted(BACKENDS), name


def test_record_passes_tolerances(record):
    assert record["tolerances"]["state"] == STATE_TOL and record["tolerances"]["reward_rtol"] == REWARD_RTOL
    for name, per_backend in record["fixtures"].items():
        for backend, r in per_backend.items():
            where = f"{name} ({backend})"
            assert r["transitions"] > 0, where
            inexact = r["qp_inexact_rows"]  # off the recording, equal to gym-anm with accurate projections
            assert r["mismatch_rows"] == [], where
            assert len(inexact) <= 0.01 * r["transitions"], where
            if not inexact:
                assert r["max_abs_state_diff"] <= STATE_TOL, where
                assert r["max_rel_reward_diff"] <= REWARD_RTOL, where
                assert r["terminations_identical"] == r["transitions"], where
            else:
                assert r["max_abs_state_diff_accurate"] <= STATE_TOL, where
            assert r["passes"], where
    assert record["command"].startswith("python -m anm_torchrl.benchmarks.parity")
    assert record["versions"]["git_commit"]
