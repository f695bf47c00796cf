"""The one parser of Hydra overrides every recipe's checks read (``anm_torchrl.overrides``)."""

import pytest

from anm_torchrl.overrides import Override, parse_override
from anm_torchrl.surrogates.pinn.presets import preset_keys
from anm_torchrl.training.network_defaults import explicit_keys
from anm_torchrl.training.recipe_errors import refuse_appended_keys


@pytest.mark.parametrize("item, expected", [
    ("model.actor_cells=[8,8]", Override("", "model.actor_cells", "[8,8]")),
    ("+foo.bar=1", Override("+", "foo.bar", "1")),
    ("++optim.lr=1e-3", Override("++", "optim.lr", "1e-3")),
    ("~logger", Override("~", "logger", "")),
    ("~eval.seed=3", Override("~", "eval.seed", "3")),
    ("+pinn_preset.power_balance.lr@pkg=2", Override("+", "pinn_preset.power_balance.lr", "2")),
    (" network = case33bw ", Override("", "network", "case33bw")),
    ("x=a=b", Override("", "x", "a=b")),  # only the first '=' splits: a value may hold '='
])
def test_parse_override(item, expected):
    assert parse_override(item) == expected


def test_three_readers_agree_on_the_key():
    """The network defaults' explicit keys, the PINN preset's keys and the ``+key`` refusal read one key from each
    override (a package suffix and every prefix dropped the same way)."""
    overrides = ["++pinn_preset.storage.lr@x=1", "~pinn_preset.generator.epochs", "pinn_preset.seed=3"]
    assert explicit_keys(overrides) == {"pinn_preset.storage.lr", "pinn_preset.generator.epochs", "pinn_preset.seed"}
    assert preset_keys(overrides) == ["storage.lr", "generator.epochs", "seed"]
    refuse_appended_keys("x.py", overrides)  # no '+key': nothing refused
    with pytest.raises(ValueError, match=r"'pinn_preset.seed' is not one of this recipe's keys"):
        refuse_appended_keys("x.py", ["+pinn_preset.seed@pkg=3"])
    refuse_appended_keys("x.py", ["+pinn_preset.seed@pkg=3"], allowed=("pinn_preset",))
