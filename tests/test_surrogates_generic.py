"""Surrogates on networks other than ANM6-Easy (issue 13 items 1, 2): the PINN chain, datasets, regressors and the
terminal classifier on registered feeders, each tied to its network. Tiny models: this checks wiring and the
network guards, not accuracy (that is ``results/pinn/pinn_generic_accuracy.json``)."""

from __future__ import annotations

import json
from pathlib import Path


import pytest
import torch

from recipe_utils import compose, load_recipe
from anm_torchrl.artifacts import ArtifactError
from anm_torchrl.data import DatasetError, default_dataset_dir, for_network, generate, load_dataset
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.grid.identity import network_key
from anm_torchrl.envs import SurrogateEnv
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import get_network
from anm_torchrl.paths import dataset_dir, surrogate_dir
from anm_torchrl.surrogates import load_surrogate
from anm_torchrl.surrogates.features import Featurizer, state_names
from anm_torchrl.surrogates.pinn import cache
from anm_torchrl.surrogates.pinn import train as tr
from anm_torchrl.surrogates.pinn.load import load_pinn

torch.set_num_threads(1)



@pytest.fixture(scope="module")
def case33():
    return network_simulator("case33bw")


def test_simulator_for_and_network_folders(case33):
    assert case33.net.n_bus == 33 and case33.n_des == 2
    anm6 = network_simulator(ANM6_EASY)
    assert network_key(network_simulator("anm6_easy")) == network_key(anm6)
    base = dataset_dir("generative", 10, 0)
    assert for_network(base, anm6) == base == default_dataset_dir("generative", 10, 0, anm6)  # ANM6 paths unchanged
    assert default_dataset_dir("generative", 10, 0, case33) == base.with_name(f"{base.name}_{network_key(case33)}")
    assert cache.default_path(case33) != cache.default_path(anm6)
    # a changed network (one branch's resistance) never reads the model cached for the original one
    c = get_network("case33bw")
    branch = c.network["branch"].copy()
    branch[3, 2] *= 1.1
    changed = GridSimulator.from_tables({**c.network, "branch": branch}, c.load_p, c.gen_p_max, c.delta_t, c.gamma,
                                        c.lamb, c.costs_clipping)
    assert cache.default_path(changed) != cache.default_path(case33)
    with pytest.raises(ValueError, match="unknown network 'nope'"):
        network_simulator("nope")


@pytest.mark.parametrize("network", ["case33bw", "simbench_mv_semiurb"])
def test_pinn_chain_on_a_feeder(network, tmp_path):
    """A smoke PINN trained on a feeder (the 115-bus one has no storage) runs as that feeder's SurrogateEnv, and its
    file is refused by another network."""
    sim = network_simulator(network)
    modules, report = tr.train_pinn(tr.preset("smoke"), sim)
    assert report["storage"].get("devices") != 0 or sim.n_des == 0
    file = tr.save_pinn(tmp_path / "pinn.safetensors", modules, tr.preset("smoke"), report, sim)
    chain = load_pinn(sim, path=file)
    env = SurrogateEnv(chain, num_envs=3, seed=0, sim=sim)
    td = env.rollout(2, break_when_any_done=False)
    assert td["next", "state"].shape == (3, 2, sim.state_dim)
    assert torch.isfinite(td["next", "reward"]).all()
    with pytest.raises(ArtifactError, match="trained on network"):
        load_pinn(network_simulator(ANM6_EASY), path=file)


def test_pinn_curtailment_counts_only_renewables():
    """cigre_mv has classical generators: the chain's curtailment (MW) is the simulator's formula with its
    renewable mask, exactly, at the chain's own generator outputs."""
    from tensordict import TensorDict

    from anm_torchrl.grid.reward import curtailment
    from anm_torchrl.surrogates.pinn.evaluate import random_transitions

    sim = network_simulator("cigre_mv")
    assert 0 < sim.renewable.sum() < sim.n_gen
    modules, report = tr.train_pinn(tr.preset("smoke"), sim)
    chain = tr_chain(sim, modules)
    state, action = random_transitions(sim, 32, seed=1)
    out = chain(TensorDict({"state": state, "action": action}, [32]))
    gen = out.get(("pinn", "gen_pq"))[..., 0]
    expected = curtailment(out.get(("pinn", "p_pot")), gen, sim.renewable) * sim.net.base_mva
    torch.testing.assert_close(out.get(("grid", "curtailment")).reshape(-1), expected, rtol=0, atol=1e-12)


def tr_chain(sim, modules):
    from anm_torchrl.surrogates.pinn.chain import build_chain

    return build_chain(sim, modules["generator"], modules["storage"], modules["power_balance"])


def test_featurizer_names_follow_the_grid_state(case33):
    f = Featurizer(case33)
    names = state_names(case33)
    assert len(names) == case33.state_dim and names[0] == "p_dev0" and names[-1] == "aux"
    assert f.names[: case33.state_dim] == names
    assert f.n_features == case33.state_dim + 2 + case33.action_dim + case33.n_load + case33.n_gen


def test_data_driven_surrogates_on_case33bw(case33, tmp_path, monkeypatch):
    """make_dataset / train_surrogate with network=case33bw write to that network's default folders; the model runs
    as its SurrogateEnv; ANM6-Easy's default folder stays empty; the dataset refuses another simulator."""
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path))
    size = 400
    for kind in ("generative", "agent"):
        # the default options: train_surrogate below asks for the default dataset, and a cached dataset made with
        # other options is refused (it was silently reused before)
        cfg = compose("make_dataset", ["network=case33bw", f"dataset={kind}", f"size={size}", "progress=false"])
        assert load_recipe("make_dataset").run(cfg) == str(default_dataset_dir(kind, size, 0, case33))
    with pytest.raises(DatasetError, match="belongs to another network"):
        load_dataset(default_dataset_dir("agent", size, 0, case33), kind="agent", sim=network_simulator(ANM6_EASY))
    cfg = compose("train_surrogate", ["network=case33bw", "surrogate=xgb", f"data.size={size}", "progress=false",
                                       "n_jobs=1", "overwrite_cache=true", "models.xgb.num_boost_round=5",
                                       "terminal.num_boost_round=5"])
    (metrics,) = load_recipe("train_surrogate").run(cfg)
    assert metrics["in_dataset"]["r2"] > 0.0  # better than predicting the mean: the fit saw this network's data
    assert (for_network(surrogate_dir("xgb", "generative"), case33) / "surrogate.json").is_file()
    assert not surrogate_dir("xgb", "generative").exists()
    model = load_surrogate("xgb", sim=case33, dataset="generative")
    env = SurrogateEnv(model, num_envs=4, seed=0, sim=case33)
    td = env.rollout(2, break_when_any_done=False)
    assert td["next", "state"].shape == (4, 2, case33.state_dim)
    with pytest.raises(FileNotFoundError, match="train_surrogate.py network=<its name> surrogate=xgb"):
        load_surrogate("xgb", sim=case33, dataset="agent", train_if_missing=False)
    with pytest.raises(FileNotFoundError, match="no trained 'xgb'"):  # ANM6-Easy never sees case33bw's model
        load_surrogate("xgb", sim=network_simulator(ANM6_EASY), dataset="generative", train_if_missing=False)


def test_generated_rows_match_the_simulator(case33):
    """A few generative rows on case33bw: the labels are the simulator's own step."""
    td, meta = generate("generative", 64, seed=3, sim=case33, chunk=64)
    nxt, tr_ = case33.step(td["state"], td["action"])
    torch.testing.assert_close(td["next_state"], nxt, rtol=0, atol=0)
    assert meta["simulator"]["n_bus"] == 33


def test_per_device_batches_keep_anm6_rows_and_scale_on_feeders():
    """The default preset counts KKT batches in device samples: ANM6-Easy keeps its 1024-point steps and
    4096-point validation sets (2 generators, 1 storage unit), a 121-generator feeder draws 17 points a step."""
    from anm_torchrl.surrogates.pinn.loop import _points
    from anm_torchrl.surrogates.pinn.tasks import TASKS

    cfg = tr.preset("default")
    for network, name, batch, val in (("anm6_easy", "generator", 1024, 4096), ("anm6_easy", "storage", 1024, 4096),
                                      ("simbench_mv_semiurb", "generator", 17, 68)):
        sim = network_simulator(network)
        task = TASKS[name](tr.build_modules(cfg, sim)[name], sim)
        mcfg = getattr(cfg, name)
        assert (_points(mcfg.batch_size, task, mcfg), _points(mcfg.val_size, task, mcfg)) == (batch, val), network


def test_recipe_trained_surrogate_loads_through_make_env(tmp_path, monkeypatch):
    """A surrogate trained by train_surrogate.py network=case33bw is the one make_env(<kind>, network="case33bw")
    loads: the recipe (simulator_for) and make_env build the feeder's simulator through one function, so both look
    under one network key (they used to differ: the recipe skipped gym-anm's defaults for the slack's P+/Q+/Q-)."""
    from anm_torchrl.training.factory import make_env

    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path))
    assert network_key(make_env("none", network="case33bw").sim) == network_key(network_simulator("case33bw"))
    size = 200  # below the default data.size: overwrite_cache=true lets it into the default folder make_env reads
    cfg = compose("train_surrogate", ["network=case33bw", "surrogate=xgb", "surrogate.dataset=generative",
                                       f"data.size={size}", "progress=false", "n_jobs=1", "overwrite_cache=true",
                                       "models.xgb.num_boost_round=3", "terminal.num_boost_round=3"])
    load_recipe("train_surrogate").run(cfg)
    env = make_env("xgb", network="case33bw", dataset="generative", seed=0)
    td = env.reset()
    td["action"] = env.action_spec.rand()
    out = env.step(td)["next"]
    assert out["state"].shape == (1, env.sim.state_dim)
    assert torch.isfinite(out["state"]).all() and torch.isfinite(out["reward"]).all()


def test_data_driven_surrogate_trains_on_first_use_on_a_generated_network(tmp_path, monkeypatch):
    """``make_env("lr", network=<a user's dict>)`` with nothing trained builds the network's dataset, fits the model
    and its terminal classifier, saves them and runs: the recipe's pipeline, no command to type. The default folder
    takes only the default dataset size; an explicit ``path`` takes any (2,000 rows here, to stay fast)."""
    import yaml

    from anm_torchrl.data.defaults import DEFAULT_FRACTIONS, DEFAULT_OPTIONS, DEFAULT_SEED, DEFAULT_SIZE
    from anm_torchrl.networks import random as rnd
    from anm_torchrl.training.factory import make_env

    recipe = yaml.safe_load((Path(__file__).resolve().parents[1] / "recipes/conf/make_dataset.yaml").read_text())
    assert (recipe["size"], recipe["seed"], tuple(recipe["fractions"])) == (DEFAULT_SIZE, DEFAULT_SEED,
                                                                            DEFAULT_FRACTIONS)
    assert {k: recipe[k] for k in DEFAULT_OPTIONS} == DEFAULT_OPTIONS  # the mirror of the recipe's defaults

    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path / "home"))
    case = rnd.generate(5, n_bus=8)
    args = dict(network=case.network, load_p=case.load_p, gen_p_max=case.gen_p_max, num_envs=4, seed=0)
    with pytest.raises(ValueError, match="size=2000 differs from the default 100000 rows"):
        make_env("lr", size=2000, progress=False, **args)
    with pytest.raises(FileNotFoundError, match="no trained 'lr'"):
        make_env("lr", path=tmp_path / "lr", progress=False, **args)  # an explicit path never trains unasked
    env = make_env("lr", path=tmp_path / "lr", size=2000, train_if_missing=True, progress=False, **args)
    meta = json.loads((tmp_path / "lr" / "surrogate.json").read_text())
    assert meta["trained_on_first_use"]["rows"] == 2000 and meta["dataset"] == "generative"
    td = env.rollout(3, break_when_any_done=False)
    assert torch.isfinite(td["next", "reward"]).all() and td["next", "state"].shape[:2] == (4, 3)
    again = make_env("lr", path=tmp_path / "lr", progress=False, **args)  # the saved model, not a second training
    assert json.loads((tmp_path / "lr" / "surrogate.json").read_text()) == meta and again is not None
