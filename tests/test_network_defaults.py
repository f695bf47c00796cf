"""Per-network defaults (``recipes/conf/per_network/*.yaml``, applied by
:func:`anm_torchrl.training.network_defaults.apply_network_defaults`): a network's entry sets every key the user
did not, a network without an entry gets ``default``, ANM6-Easy's entry changes nothing, and a bad table fails
naming what is wrong."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf, open_dict

from recipe_utils import CONF, compose

from anm_torchrl.training.config_checks import check_ppo_config, check_sac_config, check_shac_config
from anm_torchrl.training.network_defaults import apply_network_defaults, explicit_keys


def test_explicit_keys_of_hydra_overrides():
    assert explicit_keys(["network=case33bw", "+extra=1", "++env.num_envs=8", "~eval.patience", "env=sac",
                          "surrogate@x=pinn"]) == {"network", "extra", "env.num_envs", "eval.patience", "env",
                                                   "surrogate"}


def test_entry_applies_except_what_the_user_set():
    overrides = ["network=case33bw", "env.num_envs=128"]
    cfg = compose("config", overrides)
    info = apply_network_defaults(cfg, explicit_keys(overrides))
    assert info["entry"] == "case33bw" and info["kept"] == {"env.num_envs": 128}
    assert cfg.env.num_envs == 128 and cfg.env.max_steps == 200 and cfg.model.init_action == "do_nothing"
    assert cfg.loss.reward_scale == "auto" and cfg.eval.test_episodes == 4
    assert info["applied"]["collector.frames_per_batch"] == 8192 == cfg.collector.frames_per_batch


def test_a_group_choice_protects_its_keys():
    """``eval=default`` on the command line means the user chose that group as it is: none of its keys change."""
    overrides = ["network=cigre_mv", "eval=default"]
    cfg = compose("config", overrides)
    info = apply_network_defaults(cfg, explicit_keys(overrides))
    assert not any(k.startswith("eval.") for k in info["applied"]) and cfg.eval.num_episodes == 16
    assert cfg.model.init_action == "do_nothing"


def test_a_group_choice_with_the_config_folder_protects_only_what_its_file_sets():
    """``model=pinn`` (the SHAC recipe's model/pinn.yaml: the default model plus ``dynamics``) protects only
    ``model.dynamics``: the network's entry still sets the rest of the model group (case33bw's do-nothing start),
    as for ``python recipes/shac.py network=case33bw`` without the choice; ``eval=default`` still protects all."""
    assert explicit_keys(["model=pinn", "network=case33bw"], CONF) == {"model.dynamics", "network"}
    assert {f"eval.{k}" for k in compose("config", []).eval} <= explicit_keys(["eval=default"], CONF)
    assert explicit_keys(["model=no_such_option"], CONF) == {"model"}  # Hydra rejects it; nothing is guessed
    overrides = ["network=case33bw", "model=pinn"]
    cfg = compose("shac", overrides)
    info = apply_network_defaults(cfg, explicit_keys(overrides, CONF))
    assert cfg.model.dynamics == "pinn" and info["applied"]["model.init_action"] == "do_nothing"


def test_anm6_entry_changes_only_the_learning_rate_and_the_start():
    """ANM6-Easy keeps the groups' defaults but for its validated learning rate and gym-anm's initial distribution
    (the true env's own default there; a surrogate's is uniform); a given key is kept."""
    cfg = compose("config", [])
    before = OmegaConf.to_container(cfg)
    assert apply_network_defaults(cfg)["applied"] == {"optim.lr": 1.0e-4, "env.init": "gym_anm"}
    after = OmegaConf.to_container(cfg)
    assert after["optim"].pop("lr") == 1.0e-4 and before["optim"].pop("lr") == 3.0e-4
    assert after["env"].pop("init") == "gym_anm" and before["env"].pop("init") is None and after == before
    given = compose("config", ["optim.lr=3e-4", "env.init=uniform"])
    assert apply_network_defaults(given, explicit={"optim.lr", "env.init"})["applied"] == {}


@pytest.mark.parametrize("network", ["my_feeder.npz", "my_registered_feeder"])
def test_a_network_without_entry_gets_default(network):
    """A user's network (a file or a registered name) gets the ``default`` entry: the feeders' settings."""
    cfg = compose("config", [])
    cfg.network = network
    info = apply_network_defaults(cfg)
    assert info["entry"] == "default" and cfg.model.init_action == "do_nothing" and cfg.loss.reward_scale == "auto"


@pytest.mark.parametrize("config,check", [("config", check_ppo_config), ("sac", check_sac_config),
                                          ("shac", check_shac_config)])
def test_every_entry_is_a_valid_config(config, check):
    """Each entry, applied, passes the recipe's own checks (a typo in the table would fail here, not in a run).
    ``default`` is applied for an unregistered name, then checked as ANM6-Easy (the check resolves the name)."""
    for entry in compose(config, []).per_network:
        cfg = compose(config, [])
        cfg.network = "not_in_the_table" if entry == "default" else entry
        assert apply_network_defaults(cfg)["entry"] == entry
        if entry == "default":
            cfg.network = "anm6_easy"
        check(cfg)


def test_shac_backpropagates_one_step_on_the_storage_free_feeder_only():
    # simbench_mv_semiurb has no storage: horizon 1, gamma 0 is its exact objective; networks with storage keep 32
    cfg = compose("shac", ["network=simbench_mv_semiurb"])
    apply_network_defaults(cfg)
    assert (cfg.loss.horizon, cfg.loss.gamma, cfg.env.num_envs) == (1, 0.0, 256)
    for network in ("case33bw", "cigre_mv", "my_feeder.npz"):
        cfg = compose("shac", [f"network={network}"])
        apply_network_defaults(cfg)
        assert (cfg.loss.horizon, cfg.loss.gamma, cfg.model.init_action) == (32, 0.995, "do_nothing")


def test_without_storage_an_action_changes_only_its_own_step():
    # why gamma 0 is exact on simbench_mv_semiurb: the step after an action does not depend on it
    import torch

    from anm_torchrl.training.factory import make_true_env

    sim = make_true_env(1, network="simbench_mv_semiurb").sim
    assert sim.n_des == 0
    lo, hi = sim.action_bounds()
    state = torch.zeros(2, sim.state_dim, dtype=torch.float64)
    state[:, -1] = 40.0  # the time index
    first = torch.stack([lo, hi]).to(state) * 0.3 + torch.stack([hi, lo]).to(state) * 0.7
    after, tr = sim.step(state, first)
    assert not torch.allclose(tr.reward[0], tr.reward[1])  # the two actions differ in their own step
    same = ((lo + hi) / 2).to(state).expand(2, -1)
    nxt, tr2 = sim.step(after, same)
    assert bool(tr.converged.all() and tr2.converged.all())  # not two terminal (all-zero) states
    assert torch.equal(nxt[0], nxt[1]) and torch.equal(tr2.reward[0], tr2.reward[1])


def test_a_conditional_part_of_an_entry_applies_only_where_its_key_has_its_value():
    """ANM6-Easy's SHAC entry: 128 model rows through the exact model only; a given num_envs is kept."""
    runs = {}
    for overrides in (["model=exact"], ["model=pinn"], ["model=exact", "env.num_envs=64"]):
        cfg = compose("shac", overrides)
        info = apply_network_defaults(cfg, explicit_keys(overrides, CONF))
        runs[" ".join(overrides)] = (cfg.env.num_envs, info["applied"].get("env.num_envs"), info["kept"])
    assert runs == {"model=exact": (128, 128, {}), "model=pinn": (64, None, {}),
                    "model=exact env.num_envs=64": (64, None, {"env.num_envs": 64})}
    assert compose("shac", ["model=pinn"]).env.stagger is False  # the rest of the entry applies to both models
    cfg = compose("shac", ["model=pinn"])
    apply_network_defaults(cfg)
    assert cfg.env.stagger is True and cfg.loss.horizon == 64


def test_bad_tables_name_what_is_wrong():
    cfg = compose("config", ["network=case33bw"])
    with open_dict(cfg):
        cfg.per_network.case33bw.env.num_env = 3  # a typo of num_envs
    with pytest.raises(ValueError, match=r"per_network.case33bw sets keys the config does not have: env.num_env"):
        apply_network_defaults(cfg)
    cfg = compose("config", ["network=case33bw"])
    with open_dict(cfg):
        del cfg.per_network["default"]
    with pytest.raises(ValueError, match="per_network has no 'default' entry"):
        apply_network_defaults(cfg)
    cfg = compose("shac", [])
    with open_dict(cfg):
        cfg.per_network.anm6_easy["model.dynamic=exact"] = {"env": {"num_envs": 8}}  # a typo of dynamics
    with pytest.raises(ValueError, match="per_network.anm6_easy: the condition 'model.dynamic=exact' names a key the "
                                         "config does not have"):
        apply_network_defaults(cfg)
