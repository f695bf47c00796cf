"""Training cells of a study: a recipe's documented command, run in a fresh worker process through the recipe's own
config and :func:`anm_torchrl.training.protocol.train`, ``jobs`` at a time, reused when a finished run of the same
command at today's config is already in its run directory (``study_cell.json`` beside its ``summary.json``)."""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import shutil
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
#: a recipe's config name under recipes/conf
RECIPE_CONFIGS = {"ppo.py": "config", "sac.py": "sac", "shac.py": "shac"}


def command_keys(command: list[str]) -> list[str]:
    """The config keys of a cell's ``command`` (the run directory's left out)."""
    return [a for a in command[2:] if not a.startswith("hydra.run.dir=")]


def shown(command: list[str]) -> str:
    """``command`` as the README writes it (``python recipes/<x>.py ...``, the run directory left out)."""
    return " ".join(["python", f"recipes/{Path(command[1]).name}", *command_keys(command)])


def cell_config(command: list[str]):
    """``(config, network defaults)`` of a cell: the recipe's config composed with the command's keys, the network's
    defaults applied to the keys it does not set (as the recipe does)."""
    from anm_torchrl.training.network_defaults import compose_recipe_config

    return compose_recipe_config(command_keys(command), RECIPE_CONFIGS[Path(command[1]).name])


def tested_states(summary: dict) -> dict[str, Any]:
    """The test states a finished run reported on (its ``summary.json``): episodes, seed, steps, gamma, named as the
    gap tables' protocol names them."""
    test = summary["test"]
    return {"episodes": test["num_episodes"], "seed": test["seed"], "steps": test["max_steps"], "gamma": test["gamma"]}


def network_key(cfg) -> str:
    """The identity key of the network a cell's config trains on (its data, not its name: a network file rewritten
    with other tables, or a registered network whose data changed, gets another key)."""
    from anm_torchrl.grid.identity import network_key as key
    from anm_torchrl.networks import simulator

    return key(simulator(cfg.network))


def train_cell(command: list[str], run_dir: Path) -> dict[str, Any]:
    """Train one cell into ``run_dir`` in this (worker) process: its config (:func:`cell_config`) through the
    shared protocol (which checks the config first), stopping as a recipe run does on Ctrl-C or SIGTERM, and on its
    own once the study's process has gone. Returns what its marker keeps besides the command: wall time, load
    average, the network's key.

    Raises:
        RuntimeError: the run was stopped by a signal (an interrupted cell is not a finished one).
    """
    from anm_torchrl.training import protocol
    from anm_torchrl.training.signals import stop_requested, stop_signals, stop_when_orphaned

    shutil.rmtree(run_dir, ignore_errors=True)  # an unfinished earlier attempt: its logs would mix with these
    t0, load = time.perf_counter(), os.getloadavg()[0]
    cfg, defaults = cell_config(command)
    key = network_key(cfg)
    with stop_signals():
        stop_when_orphaned()
        try:
            protocol.train(cfg, run_dir, network_defaults=defaults)
        except KeyboardInterrupt:
            if not stop_requested():
                raise
        if stop_requested():  # a study's failure, not the pool's KeyboardInterrupt
            raise RuntimeError(f"{run_dir}: stopped by {stop_requested()} (interrupted, not a finished cell)")
    return {"process_wall_s": time.perf_counter() - t0, "load_avg_1min": [load, os.getloadavg()[0]],
            "network_key": key}


def finished(command: list[str], run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a finished cell of ``command`` trained with the config the command has today: the
    same command line alone would reuse a cell trained at a former default (e.g. an older per-network entry), or on
    a network whose data changed under the same name or file (its key, where the marker holds one). The table of
    per-network entries itself is not compared (another network's entry changes no cell here)."""
    from omegaconf import OmegaConf

    from anm_torchrl.training.checkpoint import config_diff
    from anm_torchrl.training.network_defaults import TABLE_KEY

    marker, summary = run_dir / "study_cell.json", run_dir / "summary.json"
    if not (summary.is_file() and marker.is_file()):
        return False
    kept = json.loads(marker.read_text())
    if kept["command"] != command:
        return False
    cfg = cell_config(command)[0]
    if kept.get("network_key") is not None and kept["network_key"] != network_key(cfg):  # none kept: not compared
        log.info("%s was trained on other network data: trained again", run_dir)
        return False
    def trains_with(config: dict) -> dict:  # the per-network table left out: its entry's values are in the other keys
        return {k: v for k, v in config.items() if k != TABLE_KEY}

    changed = config_diff(trains_with(json.loads(summary.read_text()).get("config", {})),
                          trains_with(OmegaConf.to_container(cfg, resolve=True)))
    if changed:
        log.info("%s was trained with another config (%s): trained again", run_dir, ", ".join(changed))
    return not changed


def run_cells(commands: dict[Path, list[str]], jobs: int) -> list[dict[str, Any]]:
    """Train every cell of ``commands`` (run directory -> command) not already finished (:func:`finished`),
    ``jobs`` at a time, each in a fresh process; returns how each went (``error`` holds a failed cell's traceback)."""
    todo = {d: c for d, c in commands.items() if not finished(c, d)}
    outcomes = [{"run_dir": str(d), "reused": True, "error": None} for d in commands if d not in todo]
    if not todo:
        return outcomes
    ctx = multiprocessing.get_context("spawn")  # no forked torch state; one cell per process
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, max_tasks_per_child=1) as pool:
        futures = {d: pool.submit(train_cell, c, d) for d, c in todo.items()}
        for d, fut in futures.items():
            try:
                info = fut.result()
            except Exception as err:  # noqa: BLE001 - a failed cell is reported, the others go on
                outcomes.append({"run_dir": str(d), "reused": False,
                                 "error": "".join(traceback.format_exception(err))[-2000:]})
                continue
            (d / "study_cell.json").write_text(json.dumps({"command": todo[d], **info}) + "\n")
            outcomes.append({"run_dir": str(d), "reused": False, "error": None})
    return outcomes
