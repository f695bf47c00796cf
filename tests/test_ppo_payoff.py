"""The payoff study's PPO part on records (no training): the test-state comparison it renders and merging a
ppo-only run into the full record."""

from __future__ import annotations

import json

import pytest

from anm_torchrl.experiments import payoff


def _ppo_record(dn_test: float, ppo_test: list[float]) -> dict:
    dn = {"return": -0.25, "discounted_return": -0.05, "episodes": 4, "max_steps": 1000, "eval_seed": 1}
    base = {"episodes": 4, "max_steps": 3000, "test_seed": 0, "gamma": 0.995, "cpu_s": 1.0}
    table = {"env": "none", "seeds": [0, 1], "frames": [8192, 8192], "wall_s": [60.0, 61.0],
             "best_eval_return": [-0.1, -0.1], "test_best_return": [-0.2, -0.2],
             "test_best_discounted_return": ppo_test,
             "test_fraction_of_do_nothing": [x / dn_test for x in ppo_test], "cpu_s": [50.0, 52.0],
             "threshold_reached": 2, "threshold_runs": 2, "threshold_wall_s": 18.0, "threshold_censored_at_s": []}
    return {"name": "payoff", "status": "ok", "meta": {"versions": {"git_commit": "abc"}, "config": {"ppo": {}}},
            "data": {"parts": ["ppo"], "ppo": {
                "network": "case33bw", "do_nothing": dn, "threshold_fraction": 0.5, "threshold": -0.125,
                "test_baselines": {"do_nothing": {**base, "discounted_return": dn_test},
                                   "mpc_perfect_horizon16": {**base, "discounted_return": 0.5}},
                "table": [table]}}}


def test_markdown_shows_test_fractions_of_do_nothing():
    md = payoff.markdown(_ppo_record(-0.05, [0.1, -0.02]))
    assert "4 states × 3,000 steps, seed 0, γ = 0.995" in md
    assert "| do_nothing | -0.0500 | 1.000 | 1 |" in md
    assert "| mpc_perfect_horizon16 | 0.5000 | -10.000 | 1 |" in md  # a net gain: negative fraction of the loss
    assert "| PPO none (best.pt, seeds [0, 1]) | [0.1, -0.02] | [-2.0, 0.4] | [50, 52] |" in md
    # 0.4 <= 0.5 and -2.0 (a gain) both count as at least 2x better than do-nothing
    assert "PPO none: 2/2 seeds at least 2× better than do-nothing on the test states (fraction of its discounted " \
           "loss -2.00 to 0.40" in md
    assert "Target (issue 13): PPO none: 1/2" in payoff.markdown(_ppo_record(-0.05, [-0.04, 0.1]))


def test_merge_ppo_replaces_only_the_ppo_part(tmp_path):
    full = {"name": "payoff", "status": "ok", "meta": {"versions": {}, "notes": {"cost": "c", "ppo_runs": "old"}},
            "data": {"parts": ["cost", "ppo"], "rows": [{"impl": "x"}], "ppo": {"old": True}}}
    dst, src = tmp_path / "payoff.json", tmp_path / "ppo.json"
    dst.write_text(json.dumps(full))
    src.write_text(json.dumps(_ppo_record(-0.05, [0.1, 0.1])))
    payoff.merge_ppo(src, dst, note="made by X")
    rec = json.loads(dst.read_text())
    assert rec["meta"]["notes"] == {"cost": "c", "ppo": "made by X"}
    assert rec["data"]["rows"] == [{"impl": "x"}] and rec["data"]["parts"] == ["cost", "ppo"]
    assert rec["data"]["ppo"]["network"] == "case33bw" and rec["meta"]["ppo_from"]["file"] == str(src)
    src.write_text(json.dumps({"meta": {}, "data": {"parts": ["cost"]}}))
    with pytest.raises(ValueError, match="no data.ppo"):
        payoff.merge_ppo(src, dst)
