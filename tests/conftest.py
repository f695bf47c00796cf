"""Test-session set-up: single-threaded torch and a private artifact folder (no cached models leak in)."""

import os
import shutil
import tempfile
from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)
os.environ["ANM_TORCHRL_HOME"] = tempfile.mkdtemp(prefix="anm_torchrl_test_home_")


def pytest_unconfigure(config):
    """The private artifact folder goes with the session (tests leave nothing behind in the temp dir)."""
    shutil.rmtree(os.environ["ANM_TORCHRL_HOME"], ignore_errors=True)


@pytest.fixture(scope="session")
def ppo_checkpoint(tmp_path_factory):
    """An untrained PPO checkpoint of the PPO recipe's default config, written by ``save_checkpoint``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from anm_torchrl.envs import ANM6Env
    from anm_torchrl.training.checkpoint import save_checkpoint
    from anm_torchrl.training.models import make_ppo_models

    conf = Path(__file__).resolve().parents[1] / "recipes" / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        config = OmegaConf.to_container(compose(config_name="config"), resolve=True)
    actor, critic, normalizer = make_ppo_models(ANM6Env(1, seed=0), **config["model"])
    optim = torch.optim.Adam([*actor.parameters(), *critic.parameters()])
    payload = {"algorithm": "ppo", "config": config, "actor": actor.state_dict(), "obs_norm": normalizer.stats(),
               "state": {"critic": critic.state_dict(), "optimizer": optim.state_dict()}, "frames": 32, "update": 1,
               "best_eval": None}
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "last.pt", payload)


@pytest.fixture(scope="session")
def evaluate_recipe():
    """``recipes/evaluate.py`` as a module (its ``main(argv)`` runs in-process)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("evaluate_recipe", Path(__file__).resolve().parents[1] / "recipes"
                                                  / "evaluate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
