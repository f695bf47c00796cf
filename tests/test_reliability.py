"""Issue 25: failures that were silent, cryptic or left debris behind. Each test was seen failing before its fix;
its docstring names the bug of the issue it covers."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "recipes" / "conf"
torch.set_num_threads(1)


def make_dataset_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="make_dataset", overrides=list(overrides))


# ------------------------------------------------------------------------------- bug 5: make_dataset options
@pytest.mark.parametrize("override, message", [
    ("generative.chunk=0", "generative.chunk must be an integer >= 1, got 0"),
    ("agent.num_envs=0", "agent.num_envs must be an integer >= 1, got 0"),
    ("agent.max_episode_steps=0", "agent.max_episode_steps must be an integer >= 1, got 0"),
    ("fractions=[0.5,0.5,0.5]", "fractions must be three non-negative numbers .* summing to 1"),
    ("size=0", "size must be an integer >= 1, got 0"),
    ("threads=0", "threads must be an integer >= 1, got 0"),
])
def test_make_dataset_options_checked_up_front(override, message, tmp_path, monkeypatch):
    """Bug 5: make_dataset options are range-checked before any work, one line naming the key (before: "negative
    dimension -1", ZeroDivisionError, silent renormalisation, 100,000 one-step episodes)."""
    sys.path.insert(0, str(ROOT / "recipes"))
    try:
        import make_dataset as recipe
    finally:
        sys.path.remove(str(ROOT / "recipes"))
    dataset = "agent" if override.startswith("agent.") else "generative"
    cfg = make_dataset_config(override, f"dataset={dataset}", f"out={tmp_path / 'ds'}", "progress=false")
    import anm_torchrl.networks as networks

    monkeypatch.setattr(networks, "simulator", lambda *a, **k: pytest.fail("heavy work started before the check"))
    with pytest.raises(ValueError, match=message):
        recipe.run(cfg)
    assert not (tmp_path / "ds").exists()


def test_make_dataset_default_config_passes():
    """Bug 5: the shipped defaults pass the new check, for both dataset kinds."""
    from anm_torchrl.training.config_checks import check_make_dataset_config

    check_make_dataset_config(make_dataset_config())
    check_make_dataset_config(make_dataset_config("dataset=agent"))


@pytest.mark.parametrize("kind, options, key", [
    ("generative", {"chunk": 0}, "chunk"), ("agent", {"num_envs": 0}, "num_envs"),
    ("agent", {"max_episode_steps": 0}, "max_episode_steps")])
def test_dataset_generators_refuse_bad_options(kind, options, key):
    """Bug 5: the library generators refuse the same values (callers that skip the recipe)."""
    from anm_torchrl.data import generate
    from anm_torchrl.networks import simulator

    with pytest.raises(ValueError, match=f"{key} must be an integer >= 1, got 0"):
        generate(kind, 10, 0, sim=simulator("anm6_easy"), **options)
