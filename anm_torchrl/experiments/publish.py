"""Publishing a reproduction: copy its records into a committed study folder (``results/<study>/``), explicitly.

A reproduction writes only into its own run directory. :func:`publish` copies its records (``<name>.json``, the CSV
tables) into the target folder and merges its ``run.json`` there; the caller then redraws the figures and pages
from the target's records. :func:`check_publish` refuses, before anything runs, a run that would replace the
committed record with a smaller one: another preset (a ``quick`` run over the ``full`` record), a run of only
some experiments that does not ask to be merged (``merge=true``), or any run over records another command assembled
(a folder without ``run.json``: ``results/payoff/``) — unless ``force``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.io import write_json


class PublishRefused(ValueError):
    """Publishing this run would replace (part of) the committed record with a smaller or different one."""


def committed_run(target: str | Path) -> dict[str, Any] | None:
    """The committed ``run.json`` of ``target`` (None when the folder holds no record yet)."""
    path = Path(target) / "run.json"
    return json.loads(path.read_text()) if path.is_file() else None


def check_publish(target: str | Path, preset: str, experiments: list[str], merge: bool, force: bool) -> None:
    """Raise :class:`PublishRefused` if publishing a run of ``preset`` with ``experiments`` into ``target`` would
    overwrite a committed record of another preset, or drop experiments from it, and ``force`` is not set.

    Args:
        target: the committed study folder (``results/reproduction/``, ``results/payoff/``).
        preset: the run's preset name.
        experiments: the experiments this run performs (fewer than the committed record's: a partial run).
        merge: the run is merged into the committed record experiment by experiment.
        force: publish anyway.
    """
    earlier = committed_run(target)
    if force:
        return
    if earlier is None:  # records assembled by another command (results/payoff/: python -m anm_torchrl.cli.payoff)
        present = sorted(n for n in experiments if record_files(target, n))
        if present:
            raise PublishRefused(f"publish: {target} holds committed records of {present} without a run.json (made by "
                                 "the command results/INDEX.json names for it); this run does not replace them "
                                 "(force=true to do so, or publish_dir=<another folder>)")
        return
    if earlier.get("preset") != preset:
        raise PublishRefused(f"publish: {target}/run.json holds a preset={earlier.get('preset')!r} record and this "
                             f"run is preset={preset!r}; a {preset!r} run does not replace it (force=true to do so, "
                             f"or publish_dir=<another folder>)")
    missing = sorted(set(earlier.get("experiments", {})) - set(experiments))
    if missing and not merge:
        raise PublishRefused(f"publish: this run leaves out experiments {missing} of the committed record; publishing "
                             f"it would drop their committed records. Add merge=true to replace only the "
                             f"experiments it runs (or force=true)")


def merge_into_earlier(earlier: dict, run_info: dict) -> dict:
    """``earlier`` (a ``run.json`` record) with this run's experiments merged in and listed as an update."""
    update = {k: run_info.get(k) for k in ("command", "date", "wall_s", "versions", "preset")}
    update["experiments"] = run_info["experiments"]
    earlier["experiments"] = {**earlier.get("experiments", {}), **run_info["experiments"]}
    earlier["updates"] = [*earlier.get("updates", []), update]
    return earlier


def record_files(folder: str | Path, name: str) -> list[Path]:
    """The files of experiment ``name`` in ``folder``: ``<name>.json`` and its CSV tables ``<name>_*.csv``."""
    folder = Path(folder)
    return [p for p in [folder / f"{name}.json", *sorted(folder.glob(f"{name}_*.csv"))] if p.is_file()]


def publish(run_dir: str | Path, target: str | Path, run_info: dict, merge: bool) -> dict:
    """Copy the records of ``run_dir`` (the experiments in ``run_info``) into ``target`` and write its
    ``run.json``: merged into the committed one with ``merge``, else replacing it. Returns the written run info."""
    run_dir, target = Path(run_dir), Path(target)
    target.mkdir(parents=True, exist_ok=True)
    for name in run_info["experiments"]:
        for old in record_files(target, name):
            old.unlink()  # a table the new run no longer writes must not survive next to its new record
        for f in record_files(run_dir, name):
            shutil.copy2(f, target / f.name)
    earlier = committed_run(target)
    info = merge_into_earlier(earlier, run_info) if merge and earlier is not None else dict(run_info)
    info.pop("figures", None)  # redrawn from the target's records by the caller
    write_json(target / "run.json", info)
    return info
