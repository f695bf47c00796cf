"""``--help`` of the Hydra recipes: list only the config groups a recipe composes, with their options.

Hydra's default help lists every group found under ``recipes/conf/`` (other recipes' too). A recipe whose config
selects ``hydra/help: recipe`` (``recipes/conf/hydra/help/recipe.yaml``) and calls :func:`register` before
``hydra.main`` shows, for each group of its defaults list, the options available and the one chosen.
:func:`register` also registers ``${network_label:...}``, a run directory's name part for ``network=``, and
``${or_default:value,default}`` (``value`` unless it is null: a run directory given by a key, else Hydra's).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from anm_torchrl.networks.user import network_label

RESOLVER = "recipe_groups"
LABEL_RESOLVER = "network_label"
DEFAULT_RESOLVER = "or_default"


def _source_dir(schema: str, path: str) -> Path | None:
    """The folder of a Hydra config source (schema ``file`` or ``pkg``), or None (structured configs)."""
    if schema == "file":
        return Path(path)
    if schema == "pkg":
        spec = importlib.util.find_spec(path)
        return Path(next(iter(spec.submodule_search_locations))) if spec and spec.submodule_search_locations else None
    return None


def recipe_groups(_root_: DictConfig) -> str:
    """One line per config group of the composed config: ``group: option, option (now: option)``; the options are
    the YAML files of that group in every config source (the recipe's folder and its search path)."""
    runtime = _root_.hydra.runtime
    folders = [d for d in (_source_dir(str(s.schema), str(s.path)) for s in runtime.config_sources
                           if s.provider != "hydra") if d]
    lines = []
    for group, chosen in runtime.choices.items():
        if group == "hydra" or group.startswith("hydra/"):
            continue
        options = sorted({p.stem for d in folders for p in (d / group).glob("*.yaml")})
        lines.append(f"{group}: {', '.join(options) or chosen} (now: {chosen})")
    return "\n".join(sorted(lines)) or "(none: every option is a key of the config below)"


def or_default(value, default):
    """``value``, or ``default`` where it is null (OmegaConf's ``oc.select`` keeps a null value)."""
    return default if value is None else value


def register() -> None:
    """Register the ``${recipe_groups:}``, ``${network_label:...}`` and ``${or_default:...}`` resolvers (idempotent)."""
    for name, resolver in ((RESOLVER, recipe_groups), (LABEL_RESOLVER, network_label), (DEFAULT_RESOLVER, or_default)):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, resolver)
