"""Train a data-driven surrogate of a network (and its terminal classifier), then measure it.

    python recipes/train_surrogate.py surrogate=xgb surrogate.dataset=agent
    python recipes/train_surrogate.py network=case33bw surrogate=xgb data.size=20000 overwrite_cache=true
    python recipes/train_surrogate.py surrogate=rf models.rf.n_estimators=32
    python recipes/train_surrogate.py all=true          # lr, dt, rf, xgb, dnn on generative and agent (10 models)
    python recipes/train_surrogate.py -m surrogate=lr,dt,rf,xgb,dnn surrogate.dataset=generative,agent

Steps: load both datasets (``data.*``; a missing one is generated first unless ``data.generate_missing=false``),
fit the terminal classifier on the surrogate's dataset (or reuse the cached one), fit the regressor on the
training split (validation split for early stopping), then evaluate on the held-out test split of the same
dataset *and* of the other dataset. The surrogate folder (``surrogate.path``, default
``anm_torchrl.paths.surrogate_dir(name, dataset)``, suffixed with the network key on networks other than
ANM6-Easy: ``anm_torchrl.data.for_network``) receives, in one atomic save with a manifest, the model,
``surrogate.json``, the classifier, ``metrics.json``, ``config.yaml`` and, for the DNN, TensorBoard curves in
``tb/``. The trained surrogate is then available as ``anm_torchrl.make_env(name, dataset=dataset)`` and
``python recipes/ppo.py surrogate=<name>``.

The default folder only receives a model trained on at least the default number of rows (``data.size`` of
``train_surrogate.yaml``), unless ``overwrite_cache=true``: a quick run on a small dataset never replaces the
model everyone else loads. Options: ``recipes/conf/train_surrogate.yaml``; model and classifier defaults live in
``anm_torchrl/surrogates/conf/{models,terminal}/default.yaml`` (on Hydra's search path).
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from anm_torchrl.training.recipe_help import register as register_help

CONF = Path(__file__).parent / "conf"


def run(cfg: DictConfig, sim=None, data: dict | None = None) -> list[dict]:
    """Train what ``cfg`` asks for (one surrogate, or all ten with ``all=true``) on ``sim`` (the checks'
    simulator; None: checked here) from ``data`` (:func:`load_data`'s; None: loaded here); returns the metrics."""
    from anm_torchrl.surrogates.regressors.train import train_surrogates

    return train_surrogates(cfg, OmegaConf.load(CONF / "make_dataset.yaml"), default_size(), sim, data)


def load_data(cfg: DictConfig, sim) -> dict:
    """Both datasets, loaded (or generated) and checked: an explicit folder of another network, a damaged one or
    one below the default size without ``surrogate.path`` is refused here, before any model trains."""
    from anm_torchrl.surrogates.regressors.train import load_datasets

    return load_datasets(cfg, sim, OmegaConf.load(CONF / "make_dataset.yaml"), default_size())


def check_target(path: Path) -> None:
    """``surrogate.path`` can take a saved model: a new folder in a writable place, or a saved data-driven
    surrogate's folder (replaced); a file or a folder of anything else is refused, never deleted."""
    from anm_torchrl.artifacts import check_replaceable
    from anm_torchrl.surrogates.regressors.defaults import FORMAT
    from anm_torchrl.training.recipe_errors import check_writable

    if path.exists():
        check_replaceable(path, FORMAT)
    else:
        check_writable(path.parent, "surrogate.path")


def default_size() -> int:
    """The default ``data.size`` (``recipes/conf/train_surrogate.yaml``)."""
    return int(OmegaConf.load(CONF / "train_surrogate.yaml").data.size)


register_help()  # --help lists only this recipe's config groups (recipes/conf/hydra/help/recipe.yaml)


@hydra.main(config_path="conf", config_name="train_surrogate", version_base="1.3")
def main(cfg: DictConfig) -> list[dict]:
    from hydra.core.hydra_config import HydraConfig

    from anm_torchrl.surrogates.regressors.requests import check_train_config
    from anm_torchrl.training.recipe_errors import defined_keys, refuse_appended_keys, user_errors

    run_dir = HydraConfig.get().runtime.output_dir
    with user_errors("train_surrogate.py", run_dir):  # one line naming the key, before torch is imported
        # models.<kind>.* go to the estimator (scikit-learn, XGBoost), which names a parameter it does not take
        refuse_appended_keys("train_surrogate.py", HydraConfig.get().overrides.task, allowed=("models",),
                             defined=defined_keys())
        check_train_config(cfg, default_size())
    from anm_torchrl.surrogates.regressors.train import check_train_request

    with user_errors("train_surrogate.py", run_dir):  # the network's tables, the target, the datasets
        sim = check_train_request(cfg, default_size())
        if not cfg.all and cfg.surrogate.get("path"):
            check_target(Path(str(cfg.surrogate.path)))
        data = load_data(cfg, sim)
    return run(cfg, sim, data)


if __name__ == "__main__":
    main()
