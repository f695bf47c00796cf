"""Per-network defaults of a training recipe: the entry of the run's network in the config's ``per_network`` table
(``recipes/conf/per_network/<algorithm>.yaml``, the one home), applied over the groups' defaults (ANM6-Easy's)
to every key the user did not set.

    python recipes/ppo.py network=case33bw                    # case33bw's entry: 64 envs, do-nothing start, ...
    python recipes/ppo.py network=case33bw env.num_envs=128   # the entry, but 128 envs

A network without an entry (a user's file or registered name, a generated network) gets the ``default`` entry.
An entry may hold a conditional part, ``"<dotted key>=<value>": {...}``, applied over the rest of the entry when the
config's key has that value (``"model.dynamics=exact": {env: {num_envs: 128}}``: SHAC through the exact model only).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from anm_torchrl.overrides import parse_override

log = logging.getLogger(__name__)

#: the recipes' Hydra config folder (``recipes/conf``)
RECIPE_CONF = Path(__file__).resolve().parents[2] / "recipes" / "conf"
TABLE_KEY = "per_network"
FALLBACK = "default"
_MISSING = object()


def explicit_keys(overrides: Iterable[str], conf_dir: str | Path | None = None) -> set[str]:
    """The config keys a list of Hydra overrides sets (``key=value``, ``+key=value``, ``++key=value``,
    ``~key``), e.g. ``HydraConfig.get().overrides.task``.

    A group choice ``group=option`` names the keys its option file ``<conf_dir>/<group>/<option>.yaml`` sets itself:
    ``eval=default`` all of eval's keys, ``model=pinn`` only ``model.dynamics`` (what the file takes from its defaults
    list stays the group's default, which a network's entry may set). Without ``conf_dir``, or where no such file
    is, the choice names its whole group.
    """
    keys = set()
    for item in overrides:
        _, key, choice = parse_override(item)
        if not key:
            continue
        option = Path(conf_dir, key, f"{choice}.yaml") if conf_dir is not None and choice and "." not in key else None
        if option is not None and option.is_file():
            own = OmegaConf.to_container(OmegaConf.load(option), resolve=False)
            own.pop("defaults", None)
            keys.update(f"{key}.{k}" for k in _flatten(own))
        else:
            keys.add(key)
    return keys


def _flatten(node: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out = {}
    for key, value in node.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(_flatten(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def entry_name(table: Mapping[str, Any], network: str) -> str:
    """The table entry a network gets: its own if the table has one, else ``default``."""
    return network if network in table and network != FALLBACK else FALLBACK


def network_entry(cfg: DictConfig) -> tuple[str, dict[str, Any]]:
    """``(entry name, {dotted key: value})`` of ``cfg.network`` in ``cfg.per_network``; ``("", {})`` for a config
    without a table (a recipe that has none).

    Raises:
        ValueError: the table has no ``default`` entry, or an entry names a key the config does not have.
    """
    table = cfg.get(TABLE_KEY)
    if table is None:
        return "", {}
    table = OmegaConf.to_container(table, resolve=True)
    if FALLBACK not in table:
        raise ValueError(f"{TABLE_KEY} has no '{FALLBACK}' entry (the one a network without its own gets)")
    name = entry_name(table, str(cfg.network))
    entry = dict(table[name] or {})
    parts = {k: entry.pop(k) for k in list(entry) if "=" in k}  # conditional parts: "<key>=<value>"
    values = _flatten(entry)
    for cond, part in parts.items():
        key, _, want = cond.partition("=")
        have = OmegaConf.select(cfg, key.strip(), default=_MISSING)
        if have is _MISSING:
            raise ValueError(f"{TABLE_KEY}.{name}: the condition {cond!r} names a key the config does not have")
        if str(have) == want.strip():
            values.update(_flatten(part or {}))
    missing = sorted(k for k in values if OmegaConf.select(cfg, k, default=_MISSING) is _MISSING)
    if missing:
        raise ValueError(f"{TABLE_KEY}.{name} sets keys the config does not have: {', '.join(missing)}")
    return name, values


def log_network_defaults(applied: Mapping[str, Any]) -> None:
    """Log what :func:`apply_network_defaults` applied (its return value), one INFO line."""
    if applied["applied"]:
        log.info("per-network defaults of %s (%s.%s): %s", applied["network"], TABLE_KEY, applied["entry"],
                 ", ".join(f"{k}={v}" for k, v in applied["applied"].items()))


def apply_network_defaults(cfg: DictConfig, explicit: Iterable[str] = (), log_now: bool = True) -> dict[str, Any]:
    """Set the network's entry (:func:`network_entry`) on ``cfg`` in place, except every key in ``explicit`` or
    under one of them (``env`` protects ``env.num_envs``); logged unless ``log_now`` is False (a recipe logs it
    once its config has passed its checks: :func:`log_network_defaults`).

    Returns:
        ``{"network", "entry", "applied": {key: value}, "kept": {key: the user's value}}`` (for summary.json).
    """
    name, values = network_entry(cfg)
    explicit = set(explicit)

    def given(key: str) -> bool:
        parts = key.split(".")
        return any(".".join(parts[:i]) in explicit for i in range(1, len(parts) + 1))

    init_from = (cfg.get("checkpoint") or {}).get("init_from")
    # a run given the networks it starts from (checkpoint.init_from) trains no warm start of its network's entry
    applied = {k: v for k, v in values.items() if not given(k) and not (init_from and k == "warm_start.algorithm")}
    kept = {k: OmegaConf.select(cfg, k) for k in values if given(k)}
    with open_dict(cfg):
        for key, value in applied.items():
            OmegaConf.update(cfg, key, value, merge=False)
        # PPO after a warm start (warm_start.algorithm or checkpoint.init_from) learns at warm_start.lr, unless
        # optim.lr was given
        warm = cfg.get("warm_start")
        if (warm is not None and (warm.get("algorithm") or init_from) and warm.get("lr") is not None
                and not given("optim.lr")):
            applied["optim.lr"] = warm.lr
            OmegaConf.update(cfg, "optim.lr", warm.lr, merge=False)
    out = {"network": str(cfg.network), "entry": name, "applied": applied, "kept": kept}
    if log_now:
        log_network_defaults(out)
    return out


def compose_config(overrides: Iterable[str], config_name: str = "config", conf_dir: str | Path = RECIPE_CONF):
    """A recipe's config (``<config_name>.yaml`` in ``conf_dir``: ``config`` for PPO, ``sac``, ``shac``) with Hydra
    ``overrides``, composed in-process; inside another Hydra app (``reproduce.py``) its global state is set aside
    and restored. The network's entry is not applied (:func:`compose_recipe_config` does)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup

    backup = get_gh_backup()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(str(Path(conf_dir).resolve()), version_base="1.3"):
            return compose(config_name=config_name, overrides=list(overrides))
    finally:
        restore_gh_from_backup(backup)


def compose_recipe_config(overrides: Iterable[str], config_name: str = "config",
                          conf_dir: str | Path = RECIPE_CONF) -> tuple[DictConfig, dict[str, Any]]:
    """The config a recipe trains with for a command line's ``overrides``: :func:`compose_config`, then the
    network's entry on every key the overrides do not set (as the recipe does).

    Returns:
        ``(cfg, what apply_network_defaults returns)``.
    """
    overrides = list(overrides)
    cfg = compose_config(overrides, config_name, conf_dir)
    return cfg, apply_network_defaults(cfg, explicit_keys(overrides, conf_dir))
