"""Generate a dataset of a network's transitions for the data-driven surrogates.

    python recipes/make_dataset.py dataset=generative size=100000 seed=0
    python recipes/make_dataset.py network=case33bw dataset=agent size=100000   # any registered network
    python recipes/make_dataset.py dataset=agent size=100000 seed=0 agent.num_envs=200
    python recipes/make_dataset.py -m dataset=generative,agent         # both
    python recipes/make_dataset.py dataset=agent size=2000 out=/tmp/agent_small overwrite=true

Writes ``<out>/dataset.json``, ``<out>/data/`` (TensorDict memmap) and ``<out>/manifest.json`` in one atomic save
under an exclusive lock (a second run on the same path fails at once); see ``anm_torchrl.data.storage`` for the
fields and ``anm_torchrl.data.generative`` / ``anm_torchrl.data.agent`` for how the samples are drawn.
Options: ``recipes/conf/make_dataset.yaml``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

from anm_torchrl.training.recipe_help import register as register_help

log = logging.getLogger("make_dataset")


def check(cfg: DictConfig):
    """Every range of ``cfg`` and its network, before any work (and before torch is imported); returns the
    network's simulator.

    Raises:
        ValueError: naming the offending key."""
    from anm_torchrl.training.config_checks import check_make_dataset_config

    check_make_dataset_config(cfg)
    from anm_torchrl.data import default_dataset_dir
    from anm_torchrl.networks import simulator as network_simulator
    from anm_torchrl.training.recipe_errors import check_writable

    sim = network_simulator(cfg.network)
    out = Path(cfg.out) if cfg.out else default_dataset_dir(cfg.dataset, int(cfg.size), int(cfg.seed), sim)
    if out.exists() and not cfg.overwrite:  # checked again under the writer's lock
        raise FileExistsError(f"out={out} exists; pass overwrite=true to replace it")
    if out.exists():  # overwrite replaces a dataset, never a user's file or folder (checked again at the save)
        from anm_torchrl.artifacts import check_replaceable
        from anm_torchrl.data.storage import LAYOUT

        check_replaceable(out, LAYOUT)
    check_writable(out, "out")
    return sim


def run(cfg: DictConfig, sim=None) -> str:
    """Generate and write the dataset described by ``cfg`` (on ``sim``, the result of :func:`check`, checked here
    if None); returns its folder."""
    start = time.perf_counter()
    sim = check(cfg) if sim is None else sim
    import torch

    from anm_torchrl.data import make_dataset

    torch.set_num_threads(int(cfg.threads))
    options = dict(cfg[cfg.dataset]) if cfg.get(cfg.dataset) is not None else {}
    path = make_dataset(cfg.dataset, int(cfg.size), int(cfg.seed), path=cfg.out, overwrite=bool(cfg.overwrite),
                        sim=sim, progress=bool(cfg.progress), fractions=tuple(cfg.fractions), **options)
    log.info("%s dataset (%d rows, seed %d) written to %s in %.1f s", cfg.dataset, cfg.size, cfg.seed, path,
             time.perf_counter() - start)
    return str(path)


register_help()  # --help lists only this recipe's config groups (recipes/conf/hydra/help/recipe.yaml)


@hydra.main(config_path="conf", config_name="make_dataset", version_base="1.3")
def main(cfg: DictConfig) -> str:
    from hydra.core.hydra_config import HydraConfig

    from anm_torchrl.training.recipe_errors import defined_keys, refuse_appended_keys, user_errors

    with user_errors("make_dataset.py", HydraConfig.get().runtime.output_dir):  # one line naming the key
        refuse_appended_keys("make_dataset.py", HydraConfig.get().overrides.task, defined=defined_keys())
        sim = check(cfg)
    return run(cfg, sim)


if __name__ == "__main__":
    main()
