"""Bad configs and bad files fail before any work, with errors that name what was wrong (issue 11 items 1, 6).

Every case here was reproduced before the fix: the value was accepted (``loss.gamma=1.5``), crashed after the first
update (``eval.max_steps=0``), exited 0 with an untrained checkpoint (``collector.total_frames=-5``), raised a raw
``KeyError``/``AttributeError`` (a text file as a checkpoint), only warned (another activation on resume) or
loaded silently (flipped bytes in the actor's weights).
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from anm_torchrl.training.checkpoint import (check_resume_config, load_actor, load_checkpoint, save_checkpoint,
                                             validate_checkpoint)
from anm_torchrl.training.config_checks import check_evaluate_config, check_ppo_config, check_sac_config

CONF = Path(__file__).resolve().parents[1] / "recipes" / "conf"
torch.set_num_threads(1)


def ppo_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_default_configs_pass():
    check_ppo_config(ppo_config())
    check_evaluate_config(OmegaConf.load(CONF.parent / "conf_evaluate" / "evaluate.yaml"))


@pytest.mark.parametrize("override, message", [
    ("collector.total_frames=-5", "collector.total_frames must be an integer >= 1, got -5"),
    ("collector.frames_per_batch=0", "collector.frames_per_batch must be an integer >= 1, got 0"),
    ("loss.gamma=1.5", "loss.gamma must be in [0, 1], got 1.5"),
    ("loss.gamma=-0.1", "loss.gamma must be in [0, 1], got -0.1"),  # 0 is PPO's contextual bandit (no storage)
    ("eval.gamma=-0.1", "eval.gamma must be in (0, 1], got -0.1"),
    ("loss.gae_lambda=1.1", "loss.gae_lambda must be in [0, 1], got 1.1"),
    ("eval.max_steps=0", "eval.max_steps must be an integer >= 1, got 0"),
    ("eval.num_episodes=0", "eval.num_episodes must be an integer >= 1, got 0"),
    ("eval.interval=0", "eval.interval must be an integer >= 1 or null, got 0"),
    ("checkpoint.interval=0", "checkpoint.interval must be an integer >= 1, got 0"),
    ("loss.mini_batch_size=0", "loss.mini_batch_size must be an integer >= 1, got 0"),
    ("loss.mini_batch_size=99999", "loss.mini_batch_size (99999) must be <= collector.frames_per_batch (16384)"),
    ("loss.ppo_epochs=0", "loss.ppo_epochs must be an integer >= 1, got 0"),
    ("env.max_steps=0", "env.max_steps must be an integer >= 1 or null, got 0"),
    ("env.num_envs=-1", "env.num_envs must be an integer >= 1, got -1"),
    ("optim.lr=0", "optim.lr must be in (0, inf), got 0"),
    ("optim.max_grad_norm=-1", "optim.max_grad_norm must be in (0, inf) or null, got -1"),
    ("collector.max_minutes=0", "collector.max_minutes must be in (0, inf) or null, got 0"),
    ("model.activation=gelu", "model.activation must be one of elu, leaky_relu, relu, silu, tanh, tanh_sigmoid; got 'gelu'"),
    ("model.actor_cells=[64,0]", "model.actor_cells must be a list of positive layer widths"),
    ("logger.backend=foo", "logger.backend must be one of tensorboard, csv, wandb, mlflow, null; got 'foo'"),
    ("loss.gae_every_epoch=1", "loss.gae_every_epoch must be true or false, got 1"),
    ("loss.compile=yes", "loss.compile must be true or false, got 'yes'"),
    ("collector.sync=sometimes", "collector.sync must be true or false, got 'sometimes'"),
    ("eval.test_seed=1", "eval.seed (validation states) and eval.test_seed (test states) must differ"),
    ("eval.render_interval=-1", "eval.render_interval must be an integer >= 0, got -1"),
    ("eval.background=1", "eval.background must be auto, true or false; got 1"),
    # 1 == True in Python: a flag given as 1 or 0 passed the choice (true, false) before
    ("model.state_dependent_scale=1", "model.state_dependent_scale must be one of false, true; got 1"),
    ("eval.track_test=0", "eval.track_test must be one of false, true; got 0"),
    ("collector.frames_per_batch=16383", "must be a positive multiple of env.num_envs (256)"),
    ("network=nowhere", "network: unknown network 'nowhere'; registered: ['anm6_easy', 'case33bw'"),
    ("eval.render_interval=2 logger.backend=csv", "eval.render_interval > 0 logs figures to TensorBoard"),
])
def test_ppo_config_ranges(override, message):
    with pytest.raises(ValueError) as err:
        check_ppo_config(ppo_config(*override.split()))
    assert message in str(err.value)


def test_sac_takes_a_contextual_bandit_s_discount_of_zero():
    """loss.gamma=0 (a network without storage: the critic a reward model, as PPO's and SHAC's 0) is a SAC setting;
    below 0 is refused."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        check_sac_config(compose(config_name="sac", overrides=["loss.gamma=0"]))
        with pytest.raises(ValueError, match=r"loss.gamma must be in \[0, 1\], got -0.1"):
            check_sac_config(compose(config_name="sac", overrides=["loss.gamma=-0.1"]))


@pytest.mark.parametrize("key, value, message", [
    ("gamma", 1.5, "gamma must be in (0, 1] or null, got 1.5"),
    ("steps", 0, "steps must be an integer >= 1 or null, got 0"),
    ("episodes", 0, "episodes must be an integer >= 1 or null, got 0"),
    ("env", "gym", "env must be one of exact, gym_anm, anm6; got 'gym'"),
    ("network", "nowhere", "network: unknown network 'nowhere'; registered: ['anm6_easy', 'case33bw'"),
])
def test_evaluate_config_ranges(key, value, message):
    cfg = OmegaConf.load(CONF.parent / "conf_evaluate" / "evaluate.yaml")
    cfg[key] = value
    with pytest.raises(ValueError) as err:
        check_evaluate_config(cfg)
    assert message in str(err.value)


def test_gym_anm_is_anm6_only():
    cfg = OmegaConf.load(CONF.parent / "conf_evaluate" / "evaluate.yaml")
    cfg.env, cfg.network = "gym_anm", "case33bw"
    with pytest.raises(ValueError, match="env=gym_anm runs gym-anm's ANM6Easy only"):
        check_evaluate_config(cfg)


def test_gym_anms_own_env_refuses_options_it_would_ignore():
    """surrogate=gym_anm trained from gym-anm's own start whatever env.init said (summary.json recorded the init given),
    and ignored action_mode; both are refused, in the config check and in make_env."""
    from anm_torchrl import make_env

    with pytest.raises(ValueError, match="env.init='uniform': surrogate=gym_anm starts every episode from gym-anm's"):
        check_ppo_config(ppo_config("surrogate=gym_anm", "env.init=uniform"))
    with pytest.raises(ValueError, match="env.action_mode='clip': gym-anm's own env asserts"):
        check_ppo_config(ppo_config("surrogate=gym_anm", "env.action_mode=clip"))
    with pytest.raises(ValueError, match="init='bogus'"):
        make_env("gym_anm", num_envs=1, seed=0, init="bogus")


def test_evaluate_defaults_to_the_recipes_test_states():
    """evaluate.py's episodes, seed and steps default to the test protocol's (recipes/evaluate.py test_protocol; its
    behaviour: tests/test_recipes_evaluate.py), whose seed is not the validation seed (model selection)."""
    cfg = ppo_config()
    ev = OmegaConf.load(CONF.parent / "conf_evaluate" / "evaluate.yaml")
    assert ev.seed is None and ev.steps is None and ev.episodes is None and cfg.eval.test_seed != cfg.eval.seed


# ------------------------------------------------------------------------------------------------ checkpoints
def test_flipped_bytes_in_actor_weights_fail_the_load(ppo_checkpoint, tmp_path):
    weight = load_checkpoint(ppo_checkpoint)["actor"]["module.0.module.1.2.weight"]  # the actor's 64x64 hidden layer
    raw = ppo_checkpoint.read_bytes()
    at = raw.find(weight.numpy().tobytes())
    assert at > 0, "the tensor's bytes are stored uncompressed in torch.save's zip"
    bad = bytearray(raw)
    bad[at + 400:at + 404] = bytes(b ^ 0xFF for b in bad[at + 400:at + 404])
    corrupted = tmp_path / "corrupted.pt"
    corrupted.write_bytes(bytes(bad))
    with pytest.raises(ValueError, match=r"corrupted\.pt is corrupted: content hash"):
        load_checkpoint(corrupted)


def test_nan_weights_and_malformed_checkpoints_are_refused(ppo_checkpoint, tmp_path):
    ckpt = load_checkpoint(ppo_checkpoint)
    nan = copy.deepcopy(ckpt)
    nan["actor"]["module.0.module.1.0.bias"][3] = float("nan")
    path = save_checkpoint(tmp_path / "nan.pt", {k: v for k, v in nan.items() if k != "sha256"})  # hash of NaNs
    with pytest.raises(ValueError, match=r"tensors \['actor.module.0.module.1.0.bias'\] hold NaN"):
        load_checkpoint(path)
    stringy = {k: v for k, v in ckpt.items() if k != "sha256"} | {"config": "model: tanh"}
    path = save_checkpoint(tmp_path / "string_config.pt", stringy)
    with pytest.raises(ValueError, match="malformed checkpoint: config is str"):
        load_actor(path)
    (tmp_path / "notes.txt").write_text("not a checkpoint\n")
    with pytest.raises(ValueError, match="notes.txt is not an anm_torchrl training checkpoint"):
        load_checkpoint(tmp_path / "notes.txt")
    old = {k: v for k, v in ckpt.items() if k != "sha256"} | {"format_version": 1}
    with pytest.raises(ValueError, match="unsupported checkpoint format_version 1"):
        validate_checkpoint(old)
    unknown = save_checkpoint(tmp_path / "unknown.pt", {k: v for k, v in ckpt.items() if k != "sha256"}
                              | {"algorithm": "dqn"})
    with pytest.raises(ValueError, match="trained by algorithm 'dqn', which this code does not know"):
        load_actor(unknown)


def test_resume_with_another_architecture_is_an_error(ppo_checkpoint):
    saved = load_checkpoint(ppo_checkpoint)["config"]
    for override, key in (("model.activation=relu", "model.activation: checkpoint 'tanh', this run 'relu'"),
                          ("network=case33bw", "network: checkpoint 'anm6_easy', this run 'case33bw'"),
                          ("model.actor_cells=[32,32]", "model.actor_cells: checkpoint [64, 64], this run [32, 32]")):
        new = OmegaConf.to_container(ppo_config(override), resolve=True)
        with pytest.raises(ValueError, match="another architecture") as err:
            check_resume_config(saved, new)
        assert key in str(err.value)
    new = OmegaConf.to_container(ppo_config("optim.lr=1e-3"), resolve=True)
    assert check_resume_config(saved, new) == ["optim.lr"]  # other changes are the caller's to warn about
    # a network file by another path (moved, copied, or typed as ../x/f.npz) was refused as another architecture:
    # a checkpoint with its network's key is matched by that key (check_network), not by the path as typed
    at = {**saved, "network": "/data/feeder.npz"}
    moved = {**OmegaConf.to_container(ppo_config(), resolve=True), "network": "/elsewhere/feeder_copy.npz"}
    assert check_resume_config(at, moved, network_by_key=True) == ["network"]
    with pytest.raises(ValueError, match="network: checkpoint '/data/feeder.npz'"):
        check_resume_config(at, moved)
    # a checkpoint written before an architecture flag existed had it off: resuming with it off is no change of
    # architecture, with it on is one
    older = {**saved, "model": {k: v for k, v in saved["model"].items() if k != "state_dependent_scale"}}
    same = OmegaConf.to_container(ppo_config(), resolve=True)
    assert check_resume_config(older, same) == ["model.state_dependent_scale"]
    on = OmegaConf.to_container(ppo_config("model.state_dependent_scale=true"), resolve=True)
    with pytest.raises(ValueError, match="model.state_dependent_scale: checkpoint None, this run True"):
        check_resume_config(older, on)


def test_unwritable_artifact_home_names_the_variable(monkeypatch, tmp_path):
    """A surrogate's cache write failing under ANM_TORCHRL_HOME says which variable to change; other errors pass."""
    from anm_torchrl.training import factory

    home = tmp_path / "home"
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(home))

    def denied(name, **kwargs):
        raise PermissionError(13, "Permission denied", str(home / "surrogates" / name))

    monkeypatch.setattr(factory, "load_surrogate", denied)
    with pytest.raises(PermissionError, match=r"surrogates/pinn\); set ANM_TORCHRL_HOME to a writable folder"):
        factory.make_env("pinn", num_envs=1)

    def elsewhere(name, **kwargs):
        raise PermissionError(13, "Permission denied", "/somewhere/else")

    monkeypatch.setattr(factory, "load_surrogate", elsewhere)
    with pytest.raises(PermissionError) as err:
        factory.make_env("pinn", num_envs=1)
    assert "ANM_TORCHRL_HOME" not in str(err.value)


def test_make_env_network_by_name_or_dict():
    """``make_env(network=<name>)`` and ``make_env(network=<its dict>, load_p=, gen_p_max=)`` build the same
    simulator (same content key); a dict without profiles, or an unknown name, fails with a message."""
    from anm_torchrl.networks import get_network
    from anm_torchrl.training.factory import make_env

    case = get_network("case33bw")
    by_name = make_env("none", network="case33bw", num_envs=2, seed=0)
    by_dict = make_env("none", network=case.network, load_p=case.load_p, gen_p_max=case.gen_p_max, num_envs=2,
                       seed=0, init="uniform")
    assert by_name.transition_key == by_dict.transition_key != make_env("none", num_envs=1).transition_key
    with pytest.raises(ValueError, match="a network dict needs load_p="):
        make_env("none", network=case.network)
    with pytest.raises(ValueError, match="unknown network 'nowhere'"):
        make_env("none", network="nowhere")
    with pytest.raises(ValueError, match="surrogate=gym_anm runs gym-anm's ANM6Easy only, got network='case33bw'"):
        make_env("gym_anm", network="case33bw")


@pytest.mark.parametrize("backend", ["wandb", "mlflow"])
def test_a_logger_without_its_package_fails_before_anything_runs(backend, monkeypatch):
    """TorchRL's wandb / mlflow loggers pass through; without the package the check names what to install."""
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == backend else real(name, *a))
    with pytest.raises(ValueError, match=f"logger.backend={backend} needs the {backend} package \\(pip install {backend}\\)"):
        check_ppo_config(ppo_config(f"logger.backend={backend}"))
