"""Helpers the recipe tests share: import a recipe module from ``recipes/`` and compose its Hydra config."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "recipes" / "conf"


def load_recipe(name: str):
    """The module ``recipes/<name>.py`` (recipes are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"recipe_{name}", ROOT / "recipes" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def compose(config: str, overrides: list[str]):
    """``recipes/conf/<config>.yaml`` with ``overrides``, as Hydra composes it for the recipe."""
    from hydra import compose as hydra_compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose(config, overrides=overrides)
