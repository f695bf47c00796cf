"""Guards on training a surrogate, each a bug found by review (every test fails on the code before its fix): a
training that diverges is an error, not its untrained weights saved as a model; options that were silently ignored
or taken for "not given" are refused by name."""

from __future__ import annotations

import pytest
import torch


def test_a_diverged_pinn_module_is_an_error_not_its_initial_weights(tmp_path):
    """The held-out loss never finite (lr 1e6): the loop restored the initial weights and save_pinn wrote them."""
    from anm_torchrl.networks import simulator
    from anm_torchrl.surrogates.pinn import cache
    from anm_torchrl.surrogates.pinn.presets import preset

    torch.set_num_threads(1)
    path = tmp_path / "diverged" / "pinn.safetensors"
    with pytest.raises(RuntimeError, match=r"PINN module 'power_balance' diverged: .* lower power_balance.lr"):
        cache.train_and_save(preset("smoke", power_balance={"lr": 1e6}), simulator("anm6_easy"), path=path, jobs=1)
    assert not path.exists()


def test_a_diverged_or_zero_epoch_dnn_is_an_error():
    from anm_torchrl.surrogates.dnn import train_mlp

    torch.manual_seed(0)
    x, y = torch.randn(64, 3), torch.randn(64, 2)
    with pytest.raises(RuntimeError, match="dnn: the validation MSE was not finite .* lower models.dnn.lr"):
        train_mlp(x, y, x, y, {"lr": 1e8, "max_epochs": 5})
    with pytest.raises(ValueError, match="dnn option max_epochs must be an integer >= 1, got 0"):
        train_mlp(x, y, x, y, {"max_epochs": 0})


def test_a_misspelled_loss_term_weight_is_refused():
    """``weights={"stationarty": ...}`` trained to the same weights as ``{}`` (the key was never read)."""
    from anm_torchrl.surrogates.pinn.presets import preset

    with pytest.raises(ValueError, match=r"generator.weights names 'stationarty', not a loss term .* "
                                         r"\['stationarity', 'primal', 'complementarity'\]"):
        preset("smoke", generator={"weights": {"stationarty": 1000.0}})
    with pytest.raises(ValueError, match="power_balance.weights.residual_p must be a finite number >= 0"):
        preset("smoke", power_balance={"weights": {"residual_p": -1.0}})


def test_battery_steps_of_zero_are_refused(capsys, tmp_path):
    """``--pb-steps 0`` was taken for "not given" and trained the preset's full step count."""
    from anm_torchrl.surrogates.pinn.battery import main

    with pytest.raises(SystemExit):
        main(["--seeds", "1", "--pb-steps", "0", "--out", str(tmp_path / "out"), "--model-dir", str(tmp_path)])
    assert "--pb-steps must be >= 1, got 0" in capsys.readouterr().err


def test_an_empty_artifact_home_is_the_default_not_the_current_folder(monkeypatch):
    from pathlib import Path

    from anm_torchrl.paths import artifact_home

    monkeypatch.setenv("ANM_TORCHRL_HOME", "")
    assert artifact_home() == Path.home() / ".cache" / "anm_torchrl"
