"""The PINN-on-feeders record and its rendering in the payoff study (issue 13): the accuracy table and the
generated cost/accuracy verdict read what the record says, and the committed record was measured on test
transitions of another seed than any validation set."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from anm_torchrl.experiments.payoff_report import accuracy_table, cost_verdict

ROOT = Path(__file__).resolve().parents[1]


def _entry(network, n_bus, vmag, meets, k=None):
    ev = {"n": 10_000, "vmag_mae_pu": vmag, "next_pq_rel_mae_max": 1e-4, "terminal_precision": 0.9,
          "terminal_recall": 1.0, "terminal_rate_sim": 0.005, "terminal_rate_pinn": 0.006, "pf_residual_mean": 3e-4}
    e = {"network": network, "n_bus": n_bus, "preset": "feeder", "seed": 0, "eval": {"random": ev, "expert": ev},
         "meets_targets": {"random": {"vmag_mae_pu": meets}, "expert": {"vmag_mae_pu": meets}},
         "train_cpu_s": 288.0, "train_wall_s": 841.0, "loadavg_before": [6.3, 6.0, 5.0]}
    return e if k is None else {**e, "refine_steps": k}


def _row(network, n_bus, impl, batch, us):
    return {"network": network, "n_bus": n_bus, "impl": impl, "batch": batch, "us_per_transition": us}


def test_verdict_and_table_follow_the_record():
    rec = {"data": {
        "rows": [_row("a", 6, "anm_env_numba", 1, 10.0), _row("a", 6, "pinn", 1, 30.0),
                 _row("b", 33, "anm_env_numba", 1, 50.0), _row("b", 33, "pinn", 1, 40.0)],
        "crossover": [{"impl": "pinn", "batch": 1, "crossover_n_bus": 33, "measured_n_bus": [6, 33]}],
        "pinn_accuracy": {"available": True, "data": {"networks": [_entry("a", 6, 2e-5, True, k=1),
                                                                   _entry("b", 33, 3e-3, False)]}}}}
    text = cost_verdict(rec)
    assert "anm_env_numba on a (10.0 µs)" in text and "pinn on b (40.0 µs)" in text
    assert "pinn at batch 1 from 33 buses" in text
    assert "targets on held-out test transitions on a; not on b" in text
    table = accuracy_table(rec["data"]["pinn_accuracy"]["data"]).splitlines()
    assert len(table) == 4 and "| a | 6 | feeder | 1 | 2.0e-05 / 2.0e-05 | 3.0e-04 / 3.0e-04 |" in table[2]
    assert "| no |" in table[3] and "| b | 33 | feeder | — |" in table[3]  # no chord-step count recorded
    rec["data"]["crossover"][0]["crossover_n_bus"] = None
    assert "Crossover: none" in cost_verdict(rec)


def test_committed_record_is_on_test_transitions():
    """results/pinn/pinn_generic_accuracy.json: every network evaluated with the test seed 12345 (the feeder preset was
    selected on seed 777 transitions and the training's held-out Sobol points), physics-only models."""
    rec = json.loads((ROOT / "results" / "pinn" / "pinn_generic_accuracy.json").read_text())
    assert "--seed 0" in rec["command"] and "777" not in rec["command"]
    from anm_torchrl.surrogates.pinn.generic_accuracy import measure_network
    import inspect

    assert inspect.signature(measure_network).parameters["eval_seed"].default == 12345
    for e in rec["networks"]:
        assert set(e["eval"]) == {"random", "expert"} and e["eval"]["random"]["n"] >= 10_000


def test_readme_block_renders_the_payoff_records_accuracy_part():
    from anm_torchrl.experiments.payoff_report import readme_pinn_accuracy

    acc = {"available": True, "file": "x/pinn_generic_accuracy.json",
           "data": {"networks": [_entry("a", 6, 2e-5, True, k=3)]}}
    text = readme_pinn_accuracy({"payoff": {"data": {"pinn_accuracy": acc}}})
    assert "(10,000 random, 10,000 MPC-expert; seed 12345)" in text and "| a | 6 | feeder | 3 | 2.0e-05" in text
    assert "\\|V\\| MAE" in text  # a bare |V| would split the markdown column
    assert readme_pinn_accuracy({}) == "_(PINN accuracy not measured)_"


def test_merge_replaces_one_network_and_its_command():
    from anm_torchrl.surrogates.pinn.generic_accuracy import merge

    old = {"command": "python -m m --networks a --seed 0 && python -m m --networks b --seed 0",
           "networks": [_entry("b", 33, 1e-3, False), _entry("a", 6, 1e-5, True)]}
    new = {"command": "python -m m --networks b --seed 0 --model f", "networks": [_entry("b", 33, 2e-5, True, k=2)]}
    with pytest.raises(ValueError, match="measure network 'b' twice"):
        merge([old, new])
    out = merge([old, new], replace=True)
    assert [e["network"] for e in out["networks"]] == ["a", "b"] and out["networks"][1]["refine_steps"] == 2
    assert out["command"] == "python -m m --networks a --seed 0 && python -m m --networks b --seed 0 --model f"


def test_evaluating_a_saved_model_needs_its_own_training_entry(tmp_path):
    """``--model``: the training figures come from the record entry whose training the file holds; another
    entry (other per-module figures) or no record is refused, never silently mixed."""
    import torch

    from anm_torchrl.networks import simulator as network_simulator
    from anm_torchrl.surrogates.pinn import train as tr
    from anm_torchrl.surrogates.pinn.generic_accuracy import training_of

    torch.set_num_threads(1)
    sim = network_simulator("cigre_mv")
    cfg = tr.preset("smoke")
    modules, report = tr.train_pinn(cfg, sim)
    file = tr.save_pinn(tmp_path / "pinn.safetensors", modules, cfg, report, sim)
    mods = {m: {k: v for k, v in report[m].items() if isinstance(v, (int, float))} for m in tr.MODULES}
    entry = {**_entry("cigre_mv", 15, 1e-5, True), "preset": "smoke", "modules": mods, "accepted": False,
             "acceptance_failures": ["x"], "loadavg_after": [1.0, 1.0, 1.0]}
    rec = tmp_path / "rec.json"
    rec.write_text(json.dumps({"networks": [entry]}))
    got = training_of(file, "cigre_mv", "smoke", 0, rec)
    assert got["train_cpu_s"] == 288.0 and got["modules"] == mods and got["training_from"]["record"] == str(rec)
    with pytest.raises(ValueError, match="needs training_from"):
        training_of(file, "cigre_mv", "smoke", 0, None)
    mods["power_balance"]["steps"] += 1
    rec.write_text(json.dumps({"networks": [{**entry, "modules": mods}]}))
    with pytest.raises(ValueError, match="is not the model of"):
        training_of(file, "cigre_mv", "smoke", 0, rec)
