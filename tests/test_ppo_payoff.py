"""The payoff study's PPO part on records (no training): the test-state comparison it renders and merging a
ppo-only run into the full record."""

from __future__ import annotations

import json

import pytest

from anm_torchrl.experiments import payoff, payoff_report


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
    md = payoff_report.markdown(_ppo_record(-0.05, [0.1, -0.02]))
    assert "4 states × 3,000 steps, seed 0, γ = 0.995" in md
    assert "| do_nothing | -0.0500 | 1.000 | 1 |" in md
    assert "| mpc_perfect_horizon16 | 0.5000 | -10.000 | 1 |" in md  # a net gain: negative fraction of the loss
    assert "| PPO none (best.pt, seeds [0, 1]) | [0.1, -0.02] | [-2.0, 0.4] | [50, 52] |" in md
    # 0.4 <= 0.5 and -2.0 (a gain) both count as at least 2x better than do-nothing
    assert "PPO none: 2/2 seeds at least 2× better than do-nothing on the test states (fraction of its discounted " \
           "loss -2.00 to 0.40" in md
    assert "Target (issue 13), `case33bw`: PPO none: 1/2" in payoff_report.markdown(_ppo_record(-0.05, [-0.04, 0.1]))


def test_merge_ppo_keeps_other_parts_and_networks(tmp_path):
    """A ppo-only run goes under its network; the record's former single-network part (and its note) moves under
    its own network; a second network is added beside it and a re-run replaces only its network."""
    full = {"name": "payoff", "status": "ok", "meta": {"versions": {}, "notes": {"cost": "c", "ppo": "old way"},
                                                       "ppo_from": {"file": "old.json"}},
            "data": {"parts": ["cost", "ppo"], "rows": [{"impl": "x"}], "ppo": {"network": "case33bw", "old": True}}}
    dst, src = tmp_path / "payoff.json", tmp_path / "ppo.json"
    dst.write_text(json.dumps(full))
    big = _ppo_record(-0.05, [0.1, 0.1])
    big["data"]["ppo"]["network"] = "simbench_mv_semiurb"
    src.write_text(json.dumps(big))
    payoff.merge_ppo(src, dst, note="made by X")
    rec = json.loads(dst.read_text())
    assert rec["meta"]["notes"] == {"cost": "c", "ppo_case33bw": "old way", "ppo_simbench_mv_semiurb": "made by X"}
    assert rec["data"]["rows"] == [{"impl": "x"}] and rec["data"]["parts"] == ["cost", "ppo"]
    assert "ppo" not in rec["data"]
    assert list(rec["data"]["ppo_by_network"]) == ["case33bw", "simbench_mv_semiurb"]
    assert rec["data"]["ppo_by_network"]["case33bw"]["old"] is True
    assert rec["meta"]["ppo_from"] == {"case33bw": {"file": "old.json"},
                                       "simbench_mv_semiurb": {"file": str(src), "versions": {"git_commit": "abc"},
                                                               "config": {}}}
    src.write_text(json.dumps(_ppo_record(-0.05, [0.2, 0.2])))  # case33bw again: replaces that network only
    payoff.merge_ppo(src, dst)
    rec = json.loads(dst.read_text())
    parts = payoff.ppo_parts(rec["data"])
    assert [p["network"] for p in parts] == ["case33bw", "simbench_mv_semiurb"] and "old" not in parts[0]
    md = payoff_report.markdown({**rec, "data": {**rec["data"], "rows": []}})
    assert "PPO on `case33bw`" in md and "PPO on `simbench_mv_semiurb`" in md
    src.write_text(json.dumps({"meta": {}, "data": {"parts": ["cost"]}}))
    with pytest.raises(ValueError, match="no data.ppo"):
        payoff.merge_ppo(src, dst)


def test_merge_cost_replaces_one_networks_rows(tmp_path):
    def row(net, n_bus, impl, us):
        return {"network": net, "n_bus": n_bus, "impl": impl, "batch": 1, "us_per_transition": us, "x_numba": 1.0}

    dst, src = tmp_path / "payoff.json", tmp_path / "cost.json"
    no_model = {**row("c", 115, "xgb", None), "reason": "FileNotFoundError: no trained 'xgb' surrogate"}
    dst.write_text(json.dumps({"name": "payoff", "status": "partial", "reason": "1 cost rows without a model",
                               "meta": {}, "data": {
        "rows": [row("a", 6, "anm_env_numba", 10.0), row("a", 6, "pinn", 30.0), row("c", 115, "anm_env_numba", 90.0),
                 row("c", 115, "pinn", 300.0), no_model], "crossover": []}}))
    src.write_text(json.dumps({"meta": {"versions": {"git_commit": "new"}}, "data": {
        "rows": [row("c", 115, "anm_env_numba", 95.0), row("c", 115, "pinn", 50.0)]}}))
    payoff.merge_cost(src, dst, ["c"], note="re-measured")
    rec = json.loads(dst.read_text())
    assert [(r["network"], r["us_per_transition"]) for r in rec["data"]["rows"]] == [
        ("a", 10.0), ("a", 30.0), ("c", 95.0), ("c", 50.0)]
    assert {(c["impl"], c["crossover_n_bus"]) for c in rec["data"]["crossover"]} == {("pinn", 115)}
    assert rec["meta"]["notes"] == {"cost_c": "re-measured"}
    assert (rec["status"], rec["reason"]) == ("ok", None)  # the row without a model was replaced
    with pytest.raises(ValueError, match=r"no cost rows of \['b'\]"):
        payoff.merge_cost(src, dst, ["b"])


def test_user_verdict_follows_the_record():
    """The "what this means for a user" paragraph: a surrogate that reaches the threshold sooner with its training
    counted is named; otherwise the paragraph says none did."""
    rec = _ppo_record(-0.05, [0.1, 0.1])
    t = rec["data"]["ppo"]["table"][0]
    t.update(threshold_wall_with_training_s=18.0, surrogate_train_s=0.0)
    pinn = {**t, "env": "pinn", "surrogate_train_s": 100.0, "threshold_wall_with_training_s": 110.0}
    rec["data"]["ppo"]["table"].append(pinn)
    text = payoff_report.user_verdict(rec)
    assert "`none` reached the threshold in a median 18 s" in text and "(100 s of it the surrogate's training)" in text
    assert "On no network measured did training on a surrogate reach the threshold sooner" in text
    pinn["threshold_wall_with_training_s"] = 12.0
    assert "Training on a surrogate paid off for `pinn` on `case33bw`" in payoff_report.user_verdict(rec)


def test_ppo_part_reuses_runs_and_runs_the_other_seeds(tmp_path, monkeypatch):
    """``reuse`` covers some seeds of an env: only the others are trained; the surrogate's training time is the one
    given for this part's network (another network's is never used)."""
    from anm_torchrl.experiments import ppo_runs

    base = {"env.num_envs": 4}
    net = "simbench_mv_semiurb"

    def fake_run(overrides, run_dir, timeout_s=None):
        seed = int(next(o.split("=")[1] for o in overrides if o.startswith("seed=")))
        calls.append((overrides[0], seed, timeout_s))
        curve = [{"frames": 8192, "wall_s": 10.0 + seed, "train_s": 5.0, "return": -3.0}]
        return {"ok": True, "overrides": overrides, "curve": curve, "summary": None, "load_avg_1min": [1.0, 1.0]}

    calls = []
    monkeypatch.setattr(ppo_runs, "run_ppo", fake_run)
    monkeypatch.setattr(payoff, "do_nothing_return", lambda n, b: {"return": -3.3, "episodes": 4, "max_steps": 10,
                                                                   "eval_seed": 1})
    monkeypatch.setattr(payoff, "test_baselines", lambda n, b, s: {"do_nothing": {"discounted_return": -0.7}})
    monkeypatch.setattr(payoff, "surrogate_model_ids", lambda n, s: {})
    old = fake_run(ppo_runs.ppo_overrides({"name": "none"}, 0, {**base, "network": net}), None)
    calls.clear()
    (tmp_path / "none_s0.json").write_text(json.dumps(old))
    part = payoff.ppo_part({"network": net, "envs": ["none", {"name": "pinn"}], "seeds": [0, 1, 2], "base": base,
                            "timeout_s": 300, "reuse": {"none": [str(tmp_path / "none_s0.json")]},
                            "surrogate_train_s": {"case33bw": {"pinn": 1.0}, net: {"pinn": 900.0}}}, tmp_path)
    assert calls == [("surrogate=none", 1, 300), ("surrogate=none", 2, 300), ("surrogate=pinn", 0, 300),
                     ("surrogate=pinn", 1, 300), ("surrogate=pinn", 2, 300)]
    none, pinn = part["table"]
    assert none["seeds"] == [0, 1, 2] and none["surrogate_train_s"] == 0.0 and none["threshold_reached"] == 0
    assert pinn["surrogate_train_s"] == 900.0 and none["threshold_censored_at_s"] == [10.0, 11.0, 12.0]
    part = payoff.ppo_part({"network": net, "envs": [{"name": "pinn"}], "seeds": [0], "base": base,
                            "surrogate_train_s": {"case33bw": {"pinn": 1.0}}}, tmp_path)
    assert part["table"][0]["surrogate_train_s"] is None  # not measured on this network: not borrowed


def test_baselines_are_scored_on_the_protocol_the_runs_train_with():
    """The payoff's do-nothing and test baselines read the PPO runs' ``eval`` group with the network's entry applied
    (run_ppo applies it): a feeder's 4 validation states and T = 3,000 test episodes, not ANM6-Easy's 16 states;
    an explicit key of the study's base still wins, as on a recipe's command line."""
    from anm_torchrl.experiments.ppo_runs import eval_protocol

    feeder = eval_protocol({"network": "case33bw"})
    assert (feeder.num_episodes, feeder.test_episodes, feeder.test_max_steps) == (4, 4, 3000)
    anm6 = eval_protocol({"network": "anm6_easy"})
    assert (anm6.num_episodes, anm6.test_episodes) == (16, 16)
    assert eval_protocol({"network": "case33bw", "eval.num_episodes": 2}).num_episodes == 2
