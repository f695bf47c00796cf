"""The payoff study (``anm_torchrl/experiments/payoff.py``): crossover logic, parts, a tiny cost run, and the
Hydra multirun through the submitit launcher's local executor (slow)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from anm_torchrl.experiments import payoff, payoff_report
from anm_torchrl.experiments.common import RunContext

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[1]


def _r(net, n_bus, impl, batch, us):
    return {"network": net, "n_bus": n_bus, "impl": impl, "batch": batch, "us_per_transition": us}


def test_crossover_is_the_first_bus_count_where_the_surrogate_is_cheaper():
    rows = [_r("a", 6, "anm_env_numba", 1, 10.0), _r("a", 6, "anm_env_torch", 1, 50.0), _r("a", 6, "pinn", 1, 20.0),
            _r("b", 33, "anm_env_numba", 1, 40.0), _r("b", 33, "anm_env_torch", 1, 30.0), _r("b", 33, "pinn", 1, 25.0),
            _r("c", 115, "anm_env_numba", 1, 90.0), _r("c", 115, "pinn", 1, 30.0),
            _r("a", 6, "anm_env_numba", 64, 1.0), _r("a", 6, "pinn", 64, 2.0), _r("b", 33, "pinn", 64, None)]
    out = {(c["impl"], c["batch"]): c for c in payoff.crossover(rows)}
    # at 33 buses the cheaper exact backend is torch (30) and the PINN costs 25: cheaper there first
    assert out[("pinn", 1)]["crossover_n_bus"] == 33 and out[("pinn", 1)]["measured_n_bus"] == [6, 33, 115]
    assert out[("pinn", 64)]["crossover_n_bus"] is None and out[("pinn", 64)]["measured_n_bus"] == [6]


def test_a_lower_bound_counts_only_where_it_settles_the_comparison():
    """A capped booster's cost bounds the uncapped one's from below: above the exact cost it shows the surrogate
    is dearer there; below it, it says nothing, so it is neither a crossover nor the cheapest."""
    lb = "a 20-round booster ..."
    rows = [_r("a", 6, "anm_env_numba", 1, 10.0), _r("a", 6, "xgb_generative", 1, 40.0),
            _r("c", 115, "anm_env_numba", 1, 90.0), {**_r("c", 115, "xgb_generative", 1, 200.0), "lower_bound": lb},
            _r("c", 115, "anm_env_numba", 64, 50.0), {**_r("c", 115, "xgb_generative", 64, 30.0), "lower_bound": lb}]
    for r in rows:
        r.update(load_avg_1min=1.0, x_numba=r["us_per_transition"] / (10.0 if r["network"] == "a" else
                                                                        90.0 if r["batch"] == 1 else 50.0))
    out = {(c["impl"], c["batch"]): c for c in payoff.crossover(rows)}
    assert out[("xgb_generative", 1)] == {"impl": "xgb_generative", "batch": 1, "crossover_n_bus": None,
                                          "measured_n_bus": [6, 115]}
    assert out[("xgb_generative", 64)]["crossover_n_bus"] is None and out[("xgb_generative", 64)]["measured_n_bus"] == []
    rec = {"data": {"rows": rows, "crossover": list(out.values())}}
    verdict = payoff_report.cost_verdict(rec)
    assert "batch 64: anm_env_numba on c (50.0 µs) (undetermined against xgb_generative, whose lower bound is 30.0" in verdict
    md = payoff_report.markdown(rec)
    assert "≥ 200.0 (≥ 2.22×; L1)" in md and f"- xgb_generative on c: {lb}" in md


def test_a_capped_booster_bounds_only_when_cut_while_improving():
    from anm_torchrl.surrogates._xgb import capped_prefix_reason

    defaults = {"num_boost_round": 1000, "early_stopping_rounds": 30, "max_depth": 8}
    capped = {**defaults, "num_boost_round": 20}
    assert "20-round booster" in capped_prefix_reason(capped, {"rounds": 20, "best_iteration": 19}, defaults)
    with pytest.raises(ValueError, match="kept 15 of 20 rounds"):  # early stopping's best was earlier: no bound
        capped_prefix_reason(capped, {"rounds": 20, "best_iteration": 14}, defaults)
    with pytest.raises(ValueError, match=r"differs in \['max_depth'\]"):
        capped_prefix_reason({**capped, "max_depth": 4}, {"rounds": 20, "best_iteration": 19}, defaults)
    with pytest.raises(ValueError, match="no cap"):
        capped_prefix_reason(defaults, {"rounds": 1000, "best_iteration": 999}, defaults)
    with pytest.raises(ValueError, match="needs an xgb spec with the capped model's path"):
        payoff.capped_bound({"name": "dnn", "dataset": "generative", "capped": True})


def test_unknown_part_is_refused(tmp_path):
    with pytest.raises(ValueError, match="payoff.parts"):
        payoff.run({"parts": ["cost", "speed"]}, RunContext(out_dir=tmp_path))


def test_missing_accuracy_record_is_reported(tmp_path):
    part = payoff.accuracy_part(tmp_path / "absent.json")
    assert part["available"] is False and "absent.json" in part["reason"]


def test_tiny_cost_run(tmp_path, monkeypatch):
    """Exact rows measured with a rate and a load average; a surrogate without a model is a row with a reason."""
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path / "home"))  # an empty home: no trained surrogate
    rec = payoff.run({"parts": ["cost"], "networks": ["anm6_easy"], "batch_sizes": [1, 8], "min_time": 0.0,
                      "min_steps": 2, "gym_steps": 2},
                     RunContext(out_dir=tmp_path, surrogates=({"name": "xgb", "dataset": "generative"},)))
    rows = rec["data"]["rows"]
    assert {(r["impl"], r["batch"]) for r in rows} == {("gym_anm", 1), ("anm_env_numba", 1), ("anm_env_torch", 1),
                                                        ("xgb_generative", 1), ("anm_env_numba", 8),
                                                        ("anm_env_torch", 8), ("xgb_generative", 8)}
    for r in rows:
        assert r["load_avg_1min"] >= 0
        if r["impl"] == "xgb_generative":
            assert r["us_per_transition"] is None and "xgb" in r["reason"]
        else:
            assert r["us_per_transition"] > 0 and r["warm_s"] > 0
    assert next(r for r in rows if r["impl"] == "anm_env_numba" and r["batch"] == 8)["x_numba"] == 1.0
    assert rec["status"] == "partial"


@pytest.mark.slow
def test_multirun_with_submitit_local(tmp_path):
    """``reproduce.py -m`` over two networks through ``hydra/launcher=submitit_local``: one payoff record each."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ANM_TORCHRL_HOME": str(tmp_path / "home")}
    cmd = [sys.executable, "recipes/reproduce.py", "-m", "preset=payoff", "preset.payoff.parts=[cost]",
           "preset.payoff.networks=[anm6_easy],[cigre_mv]", "preset.payoff.batch_sizes=[1]",
           "preset.payoff.min_time=0.0", "preset.payoff.gym_steps=0", "preset.surrogates=[]",
           "publish_readme=false", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
           f"hydra.sweep.dir={tmp_path / 'sweep'}"]
    subprocess.run(cmd, cwd=REPO, env=env, check=True, timeout=900)
    recs = sorted((tmp_path / "sweep").glob("*/payoff.json"))
    assert len(recs) == 2
    nets = {json.loads(p.read_text())["data"]["rows"][0]["network"] for p in recs}
    assert nets == {"anm6_easy", "cigre_mv"}


def test_results_page_holds_the_payoff_section():
    """docs/RESULTS.md's payoff section is what the generator renders from the committed results/payoff/payoff.json (a
    record merged by hand, --merge-cost / --merge-ppo, must be re-rendered into the page)."""
    from anm_torchrl.experiments.report import payoff_section

    rec = json.loads((REPO / "results" / "payoff" / "payoff.json").read_text())
    assert payoff_section(rec) in (REPO / "docs" / "RESULTS.md").read_text()


def test_a_corrupted_record_is_named_before_anything_is_merged(tmp_path):
    dst, src = tmp_path / "payoff.json", tmp_path / "cost.json"
    dst.write_text(json.dumps({"name": "payoff", "data": {"rows": []}, "meta": {}}))
    src.write_text('{"name": "payoff", "data": {"rows": [')  # cut short mid-write
    before = dst.read_text()
    with pytest.raises(ValueError, match=r"cost\.json is not valid JSON"):
        payoff.merge_cost(src, dst, ["c"])
    assert dst.read_text() == before


def test_cli_prints_the_committed_record(capsys):
    """``python -m anm_torchrl.cli.payoff <record>`` prints the record's tables (payoff_report.markdown)."""
    from anm_torchrl.cli import payoff as cli

    path = REPO / "results" / "payoff" / "payoff.json"
    cli.main([str(path)])
    assert capsys.readouterr().out == payoff_report.markdown(json.loads(path.read_text())) + "\n"
