"""Train the physics-informed surrogate of a network without a single simulator sample, then evaluate it.

    python recipes/train_pinn.py                                   # default preset -> the network's default cache
    python recipes/train_pinn.py network=case33bw                  # any registered network; default = feeder preset
    python recipes/train_pinn.py pinn_preset=paper path=artifacts/pinn_paper
    python recipes/train_pinn.py eval_only=true path=artifacts/pinn_paper
    python recipes/train_pinn.py pinn_preset=smoke path=/tmp/pinn eval.n_random=1000   # seconds

Each module (generator KKT-NN, storage KKT-NN, power-balance PINN) is trained on Sobol batches over its input
box with losses built only from ``anm_torchrl.grid.residuals`` (``anm_torchrl.surrogates.pinn.train``).
TensorBoard (``<run dir>/tb``) shows every loss term under ``surrogate/<module>/*`` and the validation errors
against the exact projection and Newton–Raphson. The evaluation (``anm_torchrl.surrogates.pinn.evaluate``)
compares the whole chain with ``GridSimulator`` on held-out random and MPC-expert transitions and writes
``pinn_eval.json`` and ``pinn_eval.md`` in the run directory.

The default cache (``path=null``) only receives a model that passes its preset's acceptance bar
(``anm_torchrl.surrogates.pinn.cache``); a smoke preset or a failed training goes to ``<run dir>/pinn.safetensors``
instead, and the run fails, unless ``overwrite_cache=true``. Presets live in
``anm_torchrl/surrogates/conf/pinn_preset`` (on Hydra's search path).
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import to_absolute_path
from omegaconf import DictConfig, OmegaConf

from anm_torchrl.training.recipe_help import register as register_help

log = logging.getLogger("train_pinn")


register_help()  # --help lists only this recipe's config groups (recipes/conf/hydra/help/recipe.yaml)


@hydra.main(config_path="conf", config_name="train_pinn", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    from anm_torchrl.networks import ANM6_EASY, check_network_name, list_networks
    from anm_torchrl.surrogates.pinn.presets import check_default_target, from_composed as check_preset, preset_keys
    from anm_torchrl.training.recipe_errors import defined_keys, refuse_appended_keys, user_errors

    run_dir = Path(HydraConfig.get().runtime.output_dir)
    composed = OmegaConf.to_container(cfg.pinn_preset, resolve=True)
    explicit = preset_keys(HydraConfig.get().overrides.task)  # kept even where equal to the named preset's
    with user_errors("train_pinn.py", run_dir):  # an unknown network or a preset value out of range: before torch
        # the preset's added keys are checked against its dataclasses
        refuse_appended_keys("train_pinn.py", HydraConfig.get().overrides.task, allowed=("pinn_preset",),
                             defined=defined_keys())
        check_network_name(cfg.network)
        if cfg.network in list_networks():  # a network file's kind is known once it is built (below)
            checked = check_preset(composed, anm6=cfg.network == ANM6_EASY, explicit=explicit, seed=int(cfg.seed))
            if cfg.path is None and not cfg.eval_only:
                check_default_target(checked, f"of {cfg.network}", bool(cfg.overwrite_cache))
    import torch

    from anm_torchrl.surrogates.pinn.cache import check_may_train_into, default_path, train_and_save
    from anm_torchrl.surrogates.pinn.load import load_pinn
    from anm_torchrl.surrogates.pinn.evaluate import REWARD_REL_WARN, evaluate_sets, format_table
    from anm_torchrl.surrogates.pinn.train import from_composed, resolve_path
    from anm_torchrl.strict_json import json_text

    torch.set_num_threads(int(cfg.threads))
    with user_errors("train_pinn.py", run_dir):  # a network file's tables, the target's rules: one line too
        from anm_torchrl.networks.resolve import check_controllable
        from anm_torchrl.surrogates.pinn.model import check_pinn_network

        sim = check_controllable(cfg.network)  # builds the simulator
        check_pinn_network(sim)  # a single-value action range makes the KKT modules' training diverge
        file = resolve_path(to_absolute_path(cfg.path)) if cfg.path is not None else default_path(sim)
        # ``default`` stands for the network's own default (the feeder preset off ANM6-Easy), with the command
        # line's changes to the composed preset kept
        train_cfg = (None if cfg.eval_only else
                     from_composed(composed, sim, explicit=explicit, seed=int(cfg.seed)))
        if cfg.eval_only:  # the model to evaluate: missing, damaged or another network's is one line, now
            load_pinn(sim, path=file, train_if_missing=False, residual_threshold=cfg.eval.residual_threshold)
        if train_cfg is not None:  # a preset without acceptance bar never replaces the default cache
            check_may_train_into(file, train_cfg, sim, bool(cfg.overwrite_cache))
            from anm_torchrl.training.recipe_errors import check_writable

            check_writable(file.parent, "path")  # e.g. under a regular file: before minutes of training
    out: dict = {"path": str(file)}
    if train_cfg is not None:
        name = train_cfg.preset
        log_dir = Path(to_absolute_path(cfg.log_dir)) if cfg.log_dir is not None else run_dir / "tb"
        log.info("training the %r preset -> %s (TensorBoard: %s)", name, file, log_dir)
        file, report = train_and_save(train_cfg, sim, path=file, overwrite_cache=bool(cfg.overwrite_cache),
                                      reject_path=run_dir / "pinn.safetensors", log_dir=log_dir,
                                      progress=bool(cfg.progress))
        log.info("trained in %.1f s: %s", report["time_s"], json_text(report, indent=1))
        out["train"] = report
    if cfg.eval.enabled:
        chain = load_pinn(sim, path=file, train_if_missing=False,
                          residual_threshold=cfg.eval.residual_threshold)
        results = evaluate_sets(chain, sim, n_random=int(cfg.eval.n_random), n_expert_envs=int(cfg.eval.expert_envs),
                                expert_steps=int(cfg.eval.expert_steps), seed=int(cfg.eval.seed))
        table = format_table(results)
        log.info("accuracy against the exact simulator:\n%s", table)
        (run_dir / "pinn_eval.md").write_text(table + "\n")
        (run_dir / "pinn_eval.json").write_text(json_text(results, indent=2))
        out["eval"] = results
        for name, res in results.items():
            if res.get("reward_rel_mae", 0.0) > REWARD_REL_WARN:
                log.warning("on its %s transitions the PINN's reward error is %.1fx the rewards' mean size "
                            "(reward_rel_mae %.3g, reward_mae %.3g): a policy trained on it learns mostly from its "
                            "error; train on the true simulator (surrogate=none) or through the exact model "
                            "(recipes/shac.py)", name, res["reward_rel_mae"], res["reward_rel_mae"], res["reward_mae"])
    return out


if __name__ == "__main__":
    main()
