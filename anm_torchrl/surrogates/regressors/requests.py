"""What ``recipes/train_surrogate.py`` checks before anything heavy is imported: the kind / dataset pair, the
default folder's size rule and the network's name (its tables are checked when the simulator is built)."""

from __future__ import annotations

from omegaconf import DictConfig

from anm_torchrl.surrogates.regressors.defaults import DATASETS, KINDS


def check_request(name: str, dataset: str | None) -> None:
    """Raise ``ValueError`` unless ``name`` is a data-driven surrogate and ``dataset`` a dataset kind."""
    if name not in KINDS:
        raise ValueError(f"train_surrogate.py trains the data-driven surrogates {list(KINDS)}, got surrogate={name!r}"
                         + (" (the PINN has its own trainer: recipes/train_pinn.py)" if name == "pinn" else ""))
    if dataset not in DATASETS:
        raise ValueError(f"surrogate.dataset must be one of {list(DATASETS)}, got {dataset!r}")


def check_default_slot(size: int, path: str | None, overwrite_cache: bool, default_size: int) -> None:
    """Raise ``ValueError`` if a model trained on ``size`` rows, fewer than the default ``data.size``
    (``default_size``), would land in its default folder (``path`` None) without ``overwrite_cache``."""
    if not path and int(size) < default_size and not overwrite_cache:
        raise ValueError(f"a dataset of {size} rows is below the default data.size={default_size}: a model trained on "
                         f"it would replace the default one in its default folder; give surrogate.path=... or "
                         f"overwrite_cache=true")


def check_train_config(cfg: DictConfig, default_size: int) -> None:
    """Everything :func:`~.train.train_surrogates` checks before building the network and loading data: the kind /
    dataset pair, the default slot's size rule, ``all`` without a path, and the network's name.

    Raises:
        ValueError: naming the offending key."""
    from anm_torchrl.networks import check_network_name

    if not cfg.all:
        check_request(cfg.surrogate.name, cfg.surrogate.get("dataset"))
    elif cfg.surrogate.get("path"):
        raise ValueError("all=true writes every model to its default folder; leave surrogate.path null")
    if not any(cfg.data.get(k) for k in DATASETS):
        check_default_slot(int(cfg.data.size), None if cfg.all else cfg.surrogate.get("path"),
                           bool(cfg.overwrite_cache), default_size)
    check_network_name(cfg.network)
