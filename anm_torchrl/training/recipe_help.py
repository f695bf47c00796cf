"""``--help`` of the Hydra recipes: list only the config groups a recipe composes, with their options.

Hydra's default help lists every group found under ``recipes/conf/`` (other recipes' too). A recipe whose config
selects ``hydra/help: recipe`` (``recipes/conf/hydra/help/recipe.yaml``) and calls :func:`register` before
``hydra.main`` shows, for each group of its defaults list, the options available and the one chosen.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

RESOLVER = "recipe_groups"


def recipe_groups(_root_: DictConfig) -> str:
    """One line per config group of the composed config: ``group: option, option (now: option)``."""
    runtime = _root_.hydra.runtime
    main = [s for s in runtime.config_sources if s.provider == "main"]
    conf = Path(str(main[0].path).removeprefix("file://")) if main else None
    lines = []
    for group, chosen in runtime.choices.items():
        if group == "hydra" or group.startswith("hydra/"):
            continue
        options = sorted(p.stem for p in (conf / group).glob("*.yaml")) if conf is not None else []
        lines.append(f"{group}: {', '.join(options) or chosen} (now: {chosen})")
    return "\n".join(sorted(lines))


def register() -> None:
    """Register the ``${recipe_groups:}`` resolver (idempotent)."""
    if not OmegaConf.has_resolver(RESOLVER):
        OmegaConf.register_new_resolver(RESOLVER, recipe_groups)
