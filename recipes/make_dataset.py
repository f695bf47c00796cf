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

import hydra
import torch
from omegaconf import DictConfig

from anm_torchrl.training.recipe_help import register as register_help

log = logging.getLogger("make_dataset")


def run(cfg: DictConfig) -> str:
    """Generate and write the dataset described by ``cfg``; returns its folder."""
    from anm_torchrl.data import make_dataset
    from anm_torchrl.networks import simulator as network_simulator
    from anm_torchrl.training.config_checks import check_make_dataset_config

    check_make_dataset_config(cfg)  # every range before any work: one line naming the key
    torch.set_num_threads(int(cfg.threads))
    options = dict(cfg[cfg.dataset]) if cfg.get(cfg.dataset) is not None else {}
    start = time.perf_counter()
    sim = network_simulator(cfg.network)
    path = make_dataset(cfg.dataset, int(cfg.size), int(cfg.seed), path=cfg.out, overwrite=bool(cfg.overwrite),
                        sim=sim, progress=bool(cfg.progress), fractions=tuple(cfg.fractions), **options)
    log.info("%s dataset (%d rows, seed %d) written to %s in %.1f s", cfg.dataset, cfg.size, cfg.seed, path,
             time.perf_counter() - start)
    return str(path)


register_help()  # --help lists only this recipe's config groups (recipes/conf/hydra/help/recipe.yaml)


@hydra.main(config_path="conf", config_name="make_dataset", version_base="1.3")
def main(cfg: DictConfig) -> str:
    return run(cfg)


if __name__ == "__main__":
    main()
