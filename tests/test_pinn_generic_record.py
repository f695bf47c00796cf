"""The PINN-on-feeders record and its rendering in the payoff study (issue 13): the accuracy table and the
generated cost/accuracy verdict read what the record says, and the committed record was measured on test
transitions of another seed than any validation set."""

from __future__ import annotations

import json
from pathlib import Path

from anm_torchrl.experiments.payoff import accuracy_table, cost_verdict

ROOT = Path(__file__).resolve().parents[1]


def _entry(network, n_bus, vmag, meets):
    ev = {"vmag_mae_pu": vmag, "next_pq_rel_mae_max": 1e-4, "terminal_precision": 0.9, "terminal_recall": 1.0,
          "terminal_rate_sim": 0.005}
    return {"network": network, "n_bus": n_bus, "preset": "feeder", "eval": {"random": ev, "expert": ev},
            "meets_targets": {"random": {"vmag_mae_pu": meets}, "expert": {"vmag_mae_pu": meets}},
            "train_cpu_s": 288.0, "train_wall_s": 841.0, "loadavg_before": [6.3, 6.0, 5.0]}


def _row(network, n_bus, impl, batch, us):
    return {"network": network, "n_bus": n_bus, "impl": impl, "batch": batch, "us_per_transition": us}


def test_verdict_and_table_follow_the_record():
    rec = {"data": {
        "rows": [_row("a", 6, "anm_env_numba", 1, 10.0), _row("a", 6, "pinn", 1, 30.0),
                 _row("b", 33, "anm_env_numba", 1, 50.0), _row("b", 33, "pinn", 1, 40.0)],
        "crossover": [{"impl": "pinn", "batch": 1, "crossover_n_bus": 33, "measured_n_bus": [6, 33]}],
        "pinn_accuracy": {"available": True, "data": {"networks": [_entry("a", 6, 2e-5, True),
                                                                   _entry("b", 33, 3e-3, False)]}}}}
    text = cost_verdict(rec)
    assert "anm_env_numba on a (10.0 µs)" in text and "pinn on b (40.0 µs)" in text
    assert "pinn at batch 1 from 33 buses" in text
    assert "targets on held-out test transitions on a; not on b" in text
    table = accuracy_table(rec["data"]["pinn_accuracy"]["data"]).splitlines()
    assert len(table) == 4 and "| a | 6 | feeder | 2.0e-05 / 2.0e-05 |" in table[2] and "| no |" in table[3]
    rec["data"]["crossover"][0]["crossover_n_bus"] = None
    assert "Crossover: none" in cost_verdict(rec)


def test_committed_record_is_on_test_transitions():
    """results/pinn_generic_accuracy.json: every network evaluated with the test seed 12345 (the feeder preset was
    selected on seed 777 transitions and the training's held-out Sobol points), physics-only models."""
    rec = json.loads((ROOT / "results" / "pinn_generic_accuracy.json").read_text())
    assert "--seed 0" in rec["command"] and "777" not in rec["command"]
    from anm_torchrl.surrogates.pinn.generic_accuracy import measure_network
    import inspect

    assert inspect.signature(measure_network).parameters["eval_seed"].default == 12345
    for e in rec["networks"]:
        assert set(e["eval"]) == {"random", "expert"} and e["eval"]["random"]["n"] >= 10_000
