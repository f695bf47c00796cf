"""The evaluation protocol's constants are defined once (``anm_torchrl.evaluation``); configs that spell them agree.

YAML cannot import a Python constant, so the recipes' configs repeat γ = 0.995 and T = 3,000: this test fails when
one of them drifts from :data:`~anm_torchrl.evaluation.EVAL_GAMMA` / :data:`~anm_torchrl.evaluation.EVAL_MAX_STEPS`.
Short smoke presets (``quick``, ``tiny``) shorten T on purpose; only their discount is checked.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from anm_torchrl.evaluation import EVAL_GAMMA, EVAL_MAX_STEPS

CONF = Path(__file__).resolve().parents[1] / "recipes" / "conf"


@pytest.mark.parametrize("file, gamma_key, steps_key", [
    ("eval/default.yaml", "gamma", "max_steps"),
    ("../conf_evaluate/evaluate.yaml", "gamma", "steps"),
    ("preset/full.yaml", "test_returns.gamma", "test_returns.max_steps"),
    ("preset/quick.yaml", "test_returns.gamma", None),
    ("preset/tiny.yaml", "test_returns.gamma", None),
])
def test_configs_spell_the_protocol_constants(file, gamma_key, steps_key):
    cfg = OmegaConf.load(CONF / file)
    assert OmegaConf.select(cfg, gamma_key, throw_on_missing=True) == EVAL_GAMMA, f"{file}: {gamma_key}"
    if steps_key is not None:
        assert OmegaConf.select(cfg, steps_key, throw_on_missing=True) == EVAL_MAX_STEPS, f"{file}: {steps_key}"

