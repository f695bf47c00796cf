"""Cached artifacts are reused only for what they were made for: dataset options and profiles, the terminal
classifier's network, a PINN folder named with a dot; datasets too small to fill the three splits are refused.
Each test failed before its fix."""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf

from anm_torchrl.artifacts import write_manifest
from anm_torchrl.data import DatasetError, default_dataset_dir, ensure_dataset, generate, make_dataset, save_dataset
from anm_torchrl.data.defaults import DEFAULT_FRACTIONS, DEFAULT_OPTIONS
from anm_torchrl.grid.identity import network_key
from anm_torchrl.networks import ANM6_EASY, get_network
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.paths import dataset_dir

torch.set_num_threads(1)
ANM6 = network_simulator(ANM6_EASY)
SMALL_AGENT = {"num_envs": 20, "waypoints": "uniform", "max_episode_steps": 5}


# ----------------------------------------------------------------------- bug 1: options of a cached dataset
def test_cached_dataset_with_other_options_is_refused(tmp_path, monkeypatch):
    """A cached agent dataset made with other generator options and split fractions is refused, naming each
    difference (before: loaded silently whatever the options, only kind, size, seed and simulator compared)."""
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path))
    path = make_dataset("agent", 400, 0, sim=ANM6, fractions=(0.5, 0.25, 0.25), **SMALL_AGENT)
    with pytest.raises(DatasetError) as err:
        ensure_dataset("agent", 400, 0, sim=ANM6, fractions=DEFAULT_FRACTIONS, **DEFAULT_OPTIONS["agent"])
    msg = str(err.value)
    for diff in ("num_envs: stored 20, requested 200", "waypoints: stored 'uniform', requested 'arcsine'",
                 "max_episode_steps: stored 5, requested 480",
                 "fractions: stored [0.5, 0.25, 0.25], requested [0.8, 0.1, 0.1]", f"delete {path}"):
        assert diff in msg, (diff, msg)
    assert "random_every" not in msg and "waypoint_every" not in msg  # the same: not listed
    # the generator's defaults count as requested when an option is not given (num_envs 100, arcsine)
    with pytest.raises(DatasetError, match="num_envs: stored 20, requested 100"):
        ensure_dataset("agent", 400, 0, sim=ANM6, fractions=(0.5, 0.25, 0.25))
    # the options it was made with load it
    td, meta = ensure_dataset("agent", 400, 0, sim=ANM6, fractions=(0.5, 0.25, 0.25), **SMALL_AGENT)
    assert meta["checksum"] and td.batch_size == (400,)


def test_cached_dataset_option_checks_keep_what_does_not_change_the_data(tmp_path, monkeypatch):
    """generative.chunk (memory and speed only) never refuses a dataset; the agent's num_envs, capped at size when
    generated, matches the uncapped request that made it."""
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path))
    make_dataset("generative", 40, 0, sim=ANM6, chunk=64)
    assert ensure_dataset("generative", 40, 0, sim=ANM6, chunk=8192)[1]["generator"]["chunk"] == 64
    make_dataset("agent", 10, 0, sim=ANM6, num_envs=200, max_episode_steps=5)  # 10 envs of one step
    assert ensure_dataset("agent", 10, 0, sim=ANM6, num_envs=200, max_episode_steps=5)[1]["generator"][
        "num_envs"] == 10


def test_dataset_without_recorded_options_is_refused(tmp_path):
    """A dataset whose metadata does not record an option (an older version's) counts as made with other options,
    as a missing simulator setting does."""
    td, meta = generate("generative", 20, 0, sim=ANM6, chunk=64)
    del meta["split_fractions"]
    path = save_dataset(td, tmp_path / "old", meta)
    with pytest.raises(DatasetError, match=r"fractions: stored none \(not recorded: made by an older version\)"):
        ensure_dataset("generative", 20, 0, path=path, sim=ANM6)


# --------------------------------------------------------------------- bug 2: one folder per profile set
def _scaled_profiles(name: str, factor: float):
    case = get_network(name)
    return network_simulator(name, load_p=case.load_p * factor, gen_p_max=case.gen_p_max * factor)


def test_default_dataset_folder_depends_on_the_profiles(tmp_path, monkeypatch):
    """Two profile sets of one network get two default dataset folders (before: keyed by the network key, which
    leaves the profiles out, so each profile set's dataset was refused by the other as 'a different simulator');
    the shipped profiles keep their folders."""
    monkeypatch.setenv("ANM_TORCHRL_HOME", str(tmp_path))
    base = dataset_dir("generative", 20, 0)
    case33 = network_simulator("case33bw")
    assert default_dataset_dir("generative", 20, 0, ANM6) == base  # unchanged defaults
    assert default_dataset_dir("generative", 20, 0, case33) == base.with_name(f"{base.name}_{network_key(case33)}")
    scaled = _scaled_profiles(ANM6_EASY, 0.9)
    assert network_key(scaled) == network_key(ANM6)  # the same network, other profiles
    assert default_dataset_dir("generative", 20, 0, scaled) != base
    scaled33 = _scaled_profiles("case33bw", 0.9)
    assert default_dataset_dir("generative", 20, 0, scaled33) != default_dataset_dir("generative", 20, 0, case33)
    first = ensure_dataset("generative", 20, 0, sim=ANM6, chunk=64)[1]
    second = ensure_dataset("generative", 20, 0, sim=scaled, chunk=64)[1]  # its own dataset, not a refusal
    assert first["simulator"]["fingerprint"] != second["simulator"]["fingerprint"]


# ------------------------------------------------------------------ bug 3: the terminal classifier's network
def _saved_classifier(path):
    from anm_torchrl.surrogates.terminal import TerminalClassifier

    g = torch.Generator().manual_seed(0)
    state, action = torch.rand(8, ANM6.state_dim, generator=g), torch.rand(8, ANM6.action_dim, generator=g)
    TerminalClassifier(sim=ANM6).fit(state, action, torch.zeros(8, dtype=torch.bool)).save(path)
    return path


def test_terminal_classifier_refuses_another_network(tmp_path):
    """A classifier trained on one network is refused on another with the same state layout, naming both network
    keys and the file (before: loaded silently)."""
    from anm_torchrl.surrogates.terminal import ModelFileError, TerminalClassifier

    path = _saved_classifier(tmp_path / "clf")
    other = network_simulator(ANM6_EASY, gamma=0.9)  # ANM6-Easy's layout, another network key
    assert other.state_dim == ANM6.state_dim and network_key(other) != network_key(ANM6)
    with pytest.raises(ModelFileError, match=f"{path / 'terminal.json'} was trained on network "
                                             f"'{network_key(ANM6)}', the simulator is network "
                                             f"'{network_key(other)}'"):
        TerminalClassifier.load(path, sim=other)
    assert json.loads((path / "terminal.json").read_text())["network_key"] == network_key(ANM6)
    assert isinstance(ModelFileError("x"), ValueError)
    assert TerminalClassifier.load(path, sim=ANM6).constant is False
    assert TerminalClassifier.load(path).constant is False  # no sim: ANM6-Easy, its network


def test_terminal_classifier_without_network_key_must_be_retrained(tmp_path):
    """A classifier file written before the network was recorded cannot be checked: refused, asking to retrain."""
    from anm_torchrl.surrogates.terminal import KIND, ModelFileError, TerminalClassifier

    path = _saved_classifier(tmp_path / "clf")
    meta = json.loads((path / "terminal.json").read_text())
    del meta["network_key"]
    (path / "terminal.json").write_text(json.dumps(meta))
    write_manifest(path, KIND)
    with pytest.raises(ModelFileError, match="records no network key: it predates the network check .*retrain"):
        TerminalClassifier.load(path, sim=ANM6)


# --------------------------------------------------------------------------- bug 4: a PINN folder with a dot
def test_pinn_path_of_a_folder_named_with_a_dot(tmp_path):
    """An existing folder whose name has a dot holds ``pinn.safetensors`` (before: taken for the file itself)."""
    from anm_torchrl.surrogates.pinn.io import FILE_NAME, read_pinn_file, resolve_path

    folder = tmp_path / "run.v2"
    folder.mkdir()
    assert resolve_path(folder) == folder / FILE_NAME
    assert resolve_path(str(folder)) == folder / FILE_NAME
    assert resolve_path(tmp_path / "model.safetensors") == tmp_path / "model.safetensors"  # a file, as before
    assert resolve_path(tmp_path / "run") == tmp_path / "run" / FILE_NAME
    with pytest.raises(FileNotFoundError, match=f"no trained PINN at {folder / FILE_NAME}"):
        read_pinn_file(folder)


# ------------------------------------------------------------------- bug 5: datasets with an empty split
@pytest.mark.parametrize("kind, size, options, message", [
    ("agent", 100, {"num_envs": 2}, "num_envs must be >= 3"),
    ("agent", 2, {"num_envs": 100}, "size must be >= 3"),
    ("generative", 2, {"chunk": 64}, "size must be >= 3"),
])
def test_generators_refuse_datasets_with_an_empty_split(kind, size, options, message):
    """Fewer than 3 split units (rows, or the agent's envs) would leave the validation or test split empty (before:
    accepted; training on it gave a NaN R² and a DNN stopped after one epoch on a validation MSE of 0)."""
    with pytest.raises(ValueError, match=message + r" \(at least one unit each for the train, validation and test"):
        generate(kind, size, 0, sim=ANM6, **options)


def test_split_codes_refuse_fewer_units_than_splits():
    from anm_torchrl.data.storage import split_codes

    with pytest.raises(ValueError, match=r"n_units must be >= 3 \(at least one unit each for the train, validation "
                                         r"and test splits\), got 2"):
        split_codes(2)
    assert split_codes(3).bincount().tolist() == [1, 1, 1]


@pytest.mark.parametrize("overrides, message", [
    ({"dataset": "agent", "agent": {"num_envs": 2}}, "agent.num_envs must be >= 3"),
    ({"dataset": "generative", "size": 2}, "size must be >= 3"),
    ({"dataset": "agent", "size": 2}, "size must be >= 3"),
])
def test_make_dataset_config_refuses_datasets_with_an_empty_split(overrides, message):
    """The recipe's up-front check refuses them too, naming the key and the minimum."""
    from pathlib import Path

    from anm_torchrl.training.config_checks import check_make_dataset_config

    conf = Path(__file__).resolve().parents[1] / "recipes" / "conf" / "make_dataset.yaml"
    cfg = OmegaConf.merge(OmegaConf.load(conf), overrides)
    with pytest.raises(ValueError, match=message):
        check_make_dataset_config(cfg)
    check_make_dataset_config(OmegaConf.merge(cfg, {"size": 3, "agent": {"num_envs": 3}}))  # the minimum passes


def test_agent_split_covers_only_envs_that_hold_rows():
    """Bug: with fewer steps than envs and a size that is not a multiple of the envs, the cut to ``size`` left the
    last envs without rows, yet they took part in the env-level split: validation or test could come out empty."""
    from anm_torchrl.data.agent import generate_agent
    from anm_torchrl.networks import simulator

    sim = simulator("anm6_easy")
    for seed in range(6):
        _, meta = generate_agent(10, seed, sim=sim, num_envs=8)  # 2 steps per env: 5 envs hold the 10 rows
        assert meta["splits"]["val"] > 0 and meta["splits"]["test"] > 0, (seed, meta["splits"])
