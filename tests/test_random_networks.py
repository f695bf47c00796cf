"""The random-network generator (``anm_torchrl.networks.random``) and the PINN battery on it
(``anm_torchrl.surrogates.pinn.battery``; the battery itself is ``slow``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from anm_torchrl.networks import random as rnd
from anm_torchrl.networks.validation import validate_network

torch.set_num_threads(1)


@pytest.mark.parametrize("seed, n_bus, meshed", [(0, 6, False), (1, 12, True), (2, 30, True), (3, 80, False)])
def test_generated_networks_are_valid_and_solvable(seed, n_bus, meshed):
    """Every draw passes the validation and the do-nothing / box-corner power flows, has every device type the
    generator promises, realistic profiles, and is the same for the same seed."""
    case = rnd.generate(seed, n_bus=n_bus, meshed=meshed)
    net = validate_network(case.network)
    kind = net["device"][:, 2]
    assert len(net["bus"]) == n_bus and case.meta["topology"] == ("meshed" if meshed else "radial")
    assert (len(net["branch"]) > n_bus - 1) == meshed
    assert (kind == -1).any() and (kind == 2).any() and (kind == 3).sum() >= 2
    assert (net["device"][kind == 3, 13] > 0).any()  # SOC_MIN > 0 somewhere
    tr = net["branch"][0]
    assert 0.95 <= tr[6] <= 1.05 and tr[3] <= 0.6 and 1 <= net["baseMVA"] <= 100
    assert case.load_p.shape == (rnd.T_DAY, (kind == -1).sum()) and (case.load_p <= 0).all()
    assert case.gen_p_max.shape == (rnd.T_DAY, np.isin(kind, (1, 2)).sum()) and (case.gen_p_max >= 0).all()
    assert rnd.check_power_flow(case.network, case.load_p, case.gen_p_max) is None
    again = rnd.generate(seed, n_bus=n_bus, meshed=meshed)
    assert np.array_equal(validate_network(again.network)["branch"], net["branch"], equal_nan=True)
    assert np.array_equal(again.load_p, case.load_p) and again.meta == case.meta


def test_generator_covers_the_device_and_branch_variety():
    """Across a few seeds: classical generators, corners present and absent, phase shifts, several bases."""
    cases = [rnd.generate(s, n_bus=10 + s) for s in range(6)]
    devs = np.concatenate([validate_network(c.network)["device"] for c in cases])
    gens = devs[np.isin(devs[:, 2], (2, 3))]
    assert (devs[:, 2] == 1).any()
    assert np.isnan(np.array([r for c in cases for r in c.network["device"] if r[2] in (2, 3)], float)[:, 8]).any()
    assert (gens[:, 8] < gens[:, 4]).any()  # a corner below PMAX
    assert len({c.meta["base_mva"] for c in cases}) > 1
    with pytest.raises(ValueError, match="n_bus must lie in 5..400"):
        rnd.generate(0, n_bus=401)
    with pytest.raises(ValueError, match="n_bus must lie in 5..400"):
        rnd.generate(0, n_bus=4)


def test_battery_case_classes_and_agreement():
    """The battery's seeds cycle through the size classes and topologies; the agreement formula."""
    from anm_torchrl.surrogates.pinn.battery import battery_case, terminal_agreement

    c = [battery_case(s).meta for s in (0, 1, 3)]
    assert [rnd.size_class(m["n_bus"]) for m in c] == ["5-15", "16-40", "5-15"]
    assert [m["topology"] for m in c] == ["radial", "radial", "meshed"]
    m = {"terminal_rate_pinn": 0.02, "terminal_rate_sim": 0.01, "terminal_precision": 0.5}
    assert terminal_agreement(m) == pytest.approx(1 - 0.01 - 0.0)


@pytest.mark.slow
def test_battery_passes_on_one_network_per_size_class(tmp_path):
    """The battery (default preset, full steps) on seeds 0, 1, 2: each network builds and meets every target."""
    from anm_torchrl.surrogates.pinn import battery

    rec = battery.main(["--seeds", "0", "1", "2", "--out", str(tmp_path), "--model-dir", str(tmp_path / "m"),
                        "--n-random", "2000"])
    for e in rec["networks"]:
        assert e["passed"], (e["seed"], e["why"])
    assert (tmp_path / "battery.md").read_text().count("## ") == 3


@pytest.mark.parametrize("seed, n_bus, topology", [(6, 5, "radial"), (9, 7, "meshed")])
def test_battery_entry_on_a_small_network_with_few_steps(tmp_path, seed, n_bus, topology):
    """One battery entry end to end on each of two small networks (100 steps per module): it builds, the Newton
    refinement meets its rule, the metrics and the table are written, and a failed target comes with its reason."""
    from anm_torchrl.surrogates.pinn import battery

    steps = {"max_steps": 100, "eval_every": 50}
    e = battery.measure(seed, tmp_path, n_random=300, overrides={m: steps for m in ("generator", "storage",
                                                                                   "power_balance")})
    assert "error" not in e, e.get("traceback")
    assert e["n_bus"] == n_bus and e["topology"] == topology
    from anm_torchrl.surrogates.pinn.refine import RULE

    assert e["refine"]["rule"] == RULE and e["refine"]["met"]
    # the reward error at the rule's k, and at the k the absolute bar alone would pick (<= the rule's: a looser bar)
    assert 0.0 <= e["reward_rel_mae"] < 1.0 and e["absolute_bar"]["k"] <= e["refine_steps"]
    assert e["absolute_bar"]["reward_rel_mae"] >= 0.0 and e["box_only"]["k"] <= e["refine_steps"]
    assert e["absolute_bar"]["k"] <= e["box_only"]["k"] and e["box_only"]["reward_rel_mae"] >= 0.0
    assert set(e["meets"]) == set(battery.TARGETS) and (e["passed"] or e["why"])
    assert 0.0 <= e["terminal_agreement"] <= 1.0 and e["vmag_mae_pu"] < 1e-2
    rec = {"created": "now", "command": "c", "machine": {"cpus": 1, "platform": "p", "torch": "t",
                                                         "torch_threads": 1}, "networks": [e]}
    assert "## 5–15 buses" in battery.markdown(rec)
    bad = dict(e, passed=False, accepted=False, acceptance_failures=["power_balance.val_vmag_mae = 1 > 0.001"])
    assert any("train that module longer" in w for w in battery.diagnose(bad))


def test_data_driven_battery_entry_on_a_small_network(tmp_path):
    """The data-driven study on battery network 6 (5 buses) with ``lr``: built on first use in an empty home (the
    100,000-row default dataset is generated), scored with the PINN battery's metrics, the PINN's row copied from its
    record, and the table written. An ordinary least-squares fit of this nonlinear map cannot reach 1 % of a rating
    everywhere, so the PINN is the better model here: the record must say so rather than pass it."""
    from anm_torchrl.experiments import data_driven_battery as ddb

    rec = ddb.run([6], ["lr"], tmp_path / "dd", n_random=500)
    (e,) = rec["networks"]
    m = e["kinds"]["lr"]
    assert m["rows"] == 100_000 and m["build_s"] > 0 and 0.0 <= m["terminal_agreement"] <= 1.0
    assert m["pq_rel_mae_max"] > e["pinn"]["pq_rel_mae_max"]
    assert "| radial (6) | 5 | lr |" in (tmp_path / "dd.md").read_text()
    assert json.loads((tmp_path / "dd.json").read_text())["command"].startswith(
        "python -m anm_torchrl.cli.data_driven_battery --seeds 6 --kinds lr")


def test_data_driven_record_refreshes_its_pinn_rows(tmp_path):
    """``--refresh-pinn`` re-reads the PINN's figures (reward MAE now among them) from a re-measured PINN battery
    record into a data-driven record, keeps its data-driven figures and says where the PINN's came from; a missing
    PINN record is refused by name."""
    import shutil

    from anm_torchrl.cli import data_driven_battery as cli

    repo = Path(__file__).resolve().parents[1]
    shutil.copy(repo / "results/pinn_battery/data_driven.json", tmp_path / "dd.json")
    before = json.loads((tmp_path / "dd.json").read_text())
    pinn = {"created": "now", "networks": [{"seed": e["seed"], "pq_rel_mae_max": 1e-6, "pq_rel_mae_mean": 1e-7,
                                            "terminal_agreement": 1.0, "train_wall_s": 9.0, "vmag_mae_pu": 1e-9,
                                            "reward_mae": 3.5e-7, "passed": True} for e in before["networks"]]}
    (tmp_path / "pinn.json").write_text(json.dumps(pinn))
    rec = cli.main(["--refresh-pinn", "--out", str(tmp_path / "dd"), "--pinn-record", str(tmp_path / "pinn.json")])
    assert [e["kinds"] for e in rec["networks"]] == [e["kinds"] for e in before["networks"]]
    assert all(e["pinn"]["reward_mae"] == 3.5e-7 for e in rec["networks"])
    assert rec["pinn_refreshed"]["record"] == str(tmp_path / "pinn.json")
    assert "| PINN (battery record) | 0.0001 | 3.50e-07 |" in (tmp_path / "dd.md").read_text()
    with pytest.raises(FileNotFoundError, match="no PINN battery record at"):
        cli.main(["--refresh-pinn", "--out", str(tmp_path / "dd"), "--pinn-record", str(tmp_path / "none.json")])
