"""Reproduce the paper's experiments (Figs. 5–12 and the four claims) and write ``docs/RESULTS.md``.

    python recipes/reproduce.py                      # preset=quick (<= 15 min on 2 cores) into results/
    python recipes/reproduce.py preset=full          # <= 3 h, 3 seeds
    python recipes/reproduce.py preset=tiny out_dir=/tmp/r results_md=/tmp/r/RESULTS.md   # smoke test
    python recipes/reproduce.py preset.experiments=[speed,rollout_error]                  # a subset

Every experiment is a module of :mod:`anm_torchrl.experiments`; each writes ``<out_dir>/<name>.json`` (status,
data, machine, versions, seeds, wall time). A piece whose code or trained files are missing is recorded as
"not available" and the run goes on. Then the figures (``<out_dir>/figures``) and the report are generated
from those files only.
"""

from __future__ import annotations

import datetime
import json
import logging
import sys
import time
import traceback
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

REPO = Path(__file__).resolve().parents[1]
log = logging.getLogger("reproduce")


def _abs(p: str | None) -> Path | None:
    if p is None:
        return None
    p = Path(str(p)).expanduser()
    return p if p.is_absolute() else REPO / p


def prepare_pinn(pcfg: dict, out_dir: Path) -> tuple[dict, list[Path]]:
    """The PINN surrogate spec to use and the TensorBoard folders where Fig. 5's losses may be.

    Uses ``pinn.path`` (or the default location) if the surrogate loads; otherwise trains it with the
    ``train_if_missing`` preset of :mod:`anm_torchrl.surrogates.pinn.train` into ``<out_dir>/artifacts/pinn``.
    """
    from anm_torchrl.experiments.common import make_env_or_reason
    from anm_torchrl.paths import surrogate_dir

    spec = {"name": "pinn", **({"path": pcfg["path"]} if pcfg.get("path") else {})}
    base = Path(pcfg["path"]).expanduser() if pcfg.get("path") else surrogate_dir("pinn")
    logs = [_abs(pcfg.get("log_dir")), out_dir / "artifacts" / "pinn_tb", base, base.parent]
    env, why = make_env_or_reason({**spec, "train_if_missing": False}, 1)  # probe: never train the default here
    if env is not None or not pcfg.get("train_if_missing"):
        return spec, logs
    art = out_dir / "artifacts" / "pinn"
    try:
        from anm_torchrl.surrogates.pinn.train import preset, save_pinn, train_pinn

        log.info("PINN not available (%s): training preset %r into %s", why, pcfg["train_if_missing"], art)
        modules, report = train_pinn(preset(pcfg["train_if_missing"]), log_dir=out_dir / "artifacts" / "pinn_tb")
        save_pinn(art, modules, preset(pcfg["train_if_missing"]), report)
        spec = {"name": "pinn", "path": str(art)}
    except Exception as err:  # noqa: BLE001
        log.warning("PINN training failed: %s", err)
    return spec, logs


def run_experiment(name: str, cfg: DictConfig, out_dir: Path, surrogates: list[dict], pinn_logs: list[Path]) -> dict:
    """Run one experiment by name; any exception becomes an ``error`` record."""
    from anm_torchrl.experiments import (accuracy, adaptability, pinn_losses, ppo_curves, rollout_error, speed,
                                         sweep)
    from anm_torchrl.experiments.io import result

    p = OmegaConf.to_container(cfg.preset, resolve=True)
    sub = p.get(name, {}) or {}
    seed = int(cfg.seed)
    t0 = time.perf_counter()
    try:
        if name == "pinn_losses":
            rec = pinn_losses.run(sub, pinn_logs)
        elif name == "speed":
            rec = speed.run(sub, surrogates, seed)
        elif name == "accuracy":
            rec = accuracy.run(sub)
        elif name == "rollout_error":
            rec = rollout_error.run(sub, surrogates, seed)
        elif name == "adaptability":
            rec = adaptability.run(sub, surrogates, seed)
        elif name == "sweep":
            sub = {**sub, "base": {**sub.get("base", {}), "threads": int(cfg.threads)}}
            if sub.get("surrogate", {}).get("name") == "pinn":
                sub["surrogate"] = next((s for s in surrogates if s["name"] == "pinn"), sub["surrogate"])
            rec = sweep.run(sub, out_dir, seed)
        elif name == "ppo_curves":
            sub = {**sub, "base": {**sub.get("base", {}), "threads": int(cfg.threads)}}
            rec = ppo_curves.run(sub, surrogates, out_dir, [int(s) for s in p.get("seeds", [0])])
        else:
            raise ValueError(f"unknown experiment {name!r}")
    except Exception as err:  # noqa: BLE001 - one experiment never stops the others
        log.exception("experiment %s failed", name)
        rec = result(name, "error", reason=f"{type(err).__name__}: {err}", traceback=traceback.format_exc())
    rec["meta"]["wall_s"] = time.perf_counter() - t0
    return rec


def write_tables(rec: dict, out_dir: Path) -> None:
    """CSV companions of the JSON records (the tables the report shows)."""
    from anm_torchrl.experiments.io import write_csv

    d, name = rec.get("data") or {}, rec["name"]
    for key in ("table", "rows", "grid", "scaling"):
        if isinstance(d.get(key), list):
            write_csv(out_dir / f"{name}_{key}.csv", d[key])


def merge_into_earlier(earlier: dict, run_info: dict) -> dict:
    """``earlier`` (an existing run.json record) with this run's experiments merged in and listed as an update."""
    update = {k: run_info[k] for k in ("command", "date", "wall_s", "versions")}
    update["experiments"] = run_info["experiments"]
    earlier["experiments"] = {**earlier.get("experiments", {}), **run_info["experiments"]}
    earlier["updates"] = [*earlier.get("updates", []), update]
    return earlier


def render(cfg: DictConfig, out_dir: Path, run_info: dict, write_run: bool = False) -> tuple[dict, Path | None]:
    """Draw every figure from ``out_dir``'s records and write ``cfg.results_md`` (if set); with ``write_run``, also
    store ``run_info`` (with the figure paths) as ``run.json``. Returns (figures, page path)."""
    from anm_torchrl.experiments import plots, report
    from anm_torchrl.experiments.io import load_results, write_json

    results = load_results(out_dir)
    figs = plots.make_all(results, out_dir / "figures")
    if write_run:
        run_info["figures"] = figs
        write_json(out_dir / "run.json", run_info)
    md = report.write_results_md(results, figs, _abs(cfg.results_md), run_info) if cfg.results_md else None
    return figs, md


@hydra.main(config_path="conf", config_name="reproduce", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    torch.set_num_threads(int(cfg.threads))
    from anm_torchrl.experiments.io import machine_info, versions, write_json

    t0 = time.perf_counter()
    out_dir = _abs(cfg.out_dir)
    if cfg.report_only:  # redraw the figures and rewrite the page from the records already in out_dir
        run_info = json.loads((out_dir / "run.json").read_text())
        figs, md = render(cfg, out_dir, run_info)
        log.info("report only: figures %s, page %s", sorted(figs), md)
        return run_info
    out_dir.mkdir(parents=True, exist_ok=True)
    p = OmegaConf.to_container(cfg.preset, resolve=True)
    surrogates = [dict(s) for s in p.get("surrogates", [])]
    pinn_spec, pinn_logs = prepare_pinn(p.get("pinn", {}) or {}, out_dir)
    surrogates = [pinn_spec if s["name"] == "pinn" else s for s in surrogates]

    run_info = {"name": "run", "status": "ok", "preset": p.get("name"), "command": " ".join(
        ["python recipes/reproduce.py", *sys.argv[1:]]), "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "seeds": {"seed": int(cfg.seed), "ppo_seeds": p.get("seeds")}, "machine": machine_info(),
        "versions": versions(), "config": OmegaConf.to_container(cfg, resolve=True), "experiments": {}}
    for name in p.get("experiments", []):
        log.info("experiment %s ...", name)
        rec = run_experiment(name, cfg, out_dir, surrogates, pinn_logs)
        rec["meta"].update(machine=run_info["machine"], versions=run_info["versions"])
        write_json(out_dir / f"{name}.json", rec)
        write_tables(rec, out_dir)
        run_info["experiments"][name] = {"status": rec["status"], "reason": rec.get("reason"),
                                         "wall_s": rec["meta"]["wall_s"]}
        log.info("experiment %s: %s (%.0f s) %s", name, rec["status"], rec["meta"]["wall_s"], rec.get("reason") or "")
    run_info["wall_s"] = wall = time.perf_counter() - t0
    if cfg.merge and (out_dir / "run.json").exists():
        run_info = merge_into_earlier(json.loads((out_dir / "run.json").read_text()), run_info)
    figs, md = render(cfg, out_dir, run_info, write_run=True)
    if md:
        log.info("wrote %s", md)
    log.info("done in %.0f s: %s", wall, {k: v["status"] for k, v in run_info["experiments"].items()})
    return run_info


if __name__ == "__main__":
    main()
