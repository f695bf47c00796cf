"""Reproduce the paper's experiments (Figs. 5–12 and the four claims) into a run directory; publish explicitly.

    python recipes/reproduce.py                      # preset=quick (<= 15 min on 2 cores) into outputs/reproduce/...
    python recipes/reproduce.py preset=full publish=true          # ~1 h; then results/, docs/RESULTS.md, README
    python recipes/reproduce.py preset=full preset.experiments=[adaptability] merge=true publish=true
    python recipes/reproduce.py preset=tiny out_dir=/tmp/r        # smoke test
    python recipes/reproduce.py report_only=true publish=true     # redraw results/ figures and pages, run nothing

Every experiment is an entry of :data:`anm_torchrl.experiments.registry.EXPERIMENTS` (one signature,
``run(cfg, ctx)``); each writes ``<out_dir>/<name>.json`` (status, data, machine, versions, seeds, wall time). A
piece whose code or trained files are missing is recorded as "not available" and the run goes on; any other
error stops the run (the records already written stay). Then the figures (``<out_dir>/figures``) and
``<out_dir>/RESULTS.md`` are generated from those files only. A run never writes outside its run directory unless ``publish=true``: then its
records are copied into their study folders under ``publish_dir`` (``results/reproduction/``, ``results/payoff/``;
merged experiment by experiment with ``merge=true``) and the figures, ``docs/RESULTS.md`` and README's result blocks
are rendered from the published records (``results/INDEX.json`` lists every record). Publishing
another preset over the committed record, or a subset of experiments without ``merge=true``, is refused before
anything runs (``force=true`` overrides).
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from anm_torchrl.training.recipe_help import register as register_help

REPO = Path(__file__).resolve().parents[1]
log = logging.getLogger("reproduce")


def _md(cfg: DictConfig, out_dir: Path) -> Path | None:
    """The run's own page: ``results_md`` relative to the run directory (None: no page)."""
    if cfg.results_md is None:
        return None
    p = Path(str(cfg.results_md)).expanduser()
    return p if p.is_absolute() else out_dir / p


def _abs(p: str | None) -> Path | None:
    """A publish target: relative to the repository (results/, docs/, README.md)."""
    if p is None:
        return None
    p = Path(str(p)).expanduser()
    return p if p.is_absolute() else REPO / p


def _run_dir(cfg: DictConfig) -> Path:
    """The run's folder: ``out_dir`` relative to where the command was typed (as every recipe's paths), which is
    also Hydra's run directory (its log), else the folder Hydra made under ``outputs/reproduce``."""
    from hydra.core.hydra_config import HydraConfig

    return (Path(str(cfg.out_dir)).expanduser().resolve() if cfg.out_dir is not None
            else Path(HydraConfig.get().runtime.output_dir))


def prepare_pinn(pcfg: dict, out_dir: Path) -> tuple[dict, list[Path], dict | None]:
    """The PINN surrogate spec to use, the TensorBoard folders where Fig. 5's losses may be, and the time this run
    spent training it, ``{"wall_s", "cpu_s"}`` (None when an already trained PINN is used: not timed here).
    ``cpu_s`` is this process's CPU time: with one torch thread it is the wall time of an idle machine.

    Uses ``pinn.path`` (or the default cache) if the surrogate loads; otherwise trains the ``train_if_missing``
    preset into the default cache — or, for a preset without acceptance bar (``smoke``), which never enters the
    default cache, into ``<out_dir>/artifacts/pinn`` — (its TensorBoard run in ``<out_dir>/artifacts/pinn_tb``),
    timing it.
    """
    from anm_torchrl.experiments.common import make_env_or_reason
    from anm_torchrl.paths import surrogate_dir

    spec = {"name": "pinn", **({"path": pcfg["path"]} if pcfg.get("path") else {})}
    base = Path(pcfg["path"]).expanduser() if pcfg.get("path") else surrogate_dir("pinn")
    tb = out_dir / "artifacts" / "pinn_tb"
    logs = [_abs(pcfg.get("log_dir")), tb, base, base.parent]
    env, why = make_env_or_reason({**spec, "train_if_missing": False}, 1)  # probe: never train here by accident
    if env is not None or not pcfg.get("train_if_missing"):
        return spec, logs, None
    from anm_torchrl.surrogates import load_surrogate

    from anm_torchrl.surrogates.pinn.presets import preset as pinn_preset

    if not pcfg.get("path") and not pinn_preset(str(pcfg["train_if_missing"])).acceptance:
        spec["path"] = str(out_dir / "artifacts" / "pinn")  # no acceptance bar (smoke): never the default cache
    log.info("PINN not available (%s): training preset %r", why, pcfg["train_if_missing"])
    t0, c0 = time.perf_counter(), time.process_time()
    load_surrogate("pinn", train_if_missing=True, preset=str(pcfg["train_if_missing"]), log_dir=tb, progress=False,
                   **({"path": spec["path"]} if spec.get("path") else {}))
    return spec, logs, {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def run_experiment(name: str, cfg: DictConfig, ctx) -> dict:
    """Run experiment ``name`` of the registry on its preset section with the run's context, timed. An experiment
    records what it cannot measure ("not available"); any other error propagates: the records already written
    stay in the run directory, and ``merge=true`` re-runs the rest."""
    from anm_torchrl.experiments import registry

    sub = OmegaConf.to_container(cfg.preset, resolve=True).get(name, {}) or {}
    t0 = time.perf_counter()
    rec = registry.get(name)(sub, ctx)
    rec["meta"]["wall_s"] = time.perf_counter() - t0
    return rec


def write_tables(rec: dict, out_dir: Path) -> None:
    """CSV companions of the JSON records (the tables the report shows)."""
    from anm_torchrl.experiments.io import write_csv

    d, name = rec.get("data") or {}, rec["name"]
    for key in ("table", "rows", "grid", "scaling"):
        if isinstance(d.get(key), list):
            write_csv(out_dir / f"{name}_{key}.csv", d[key])


def render(out_dir: Path, results_md: Path | None, run_info: dict, write_run: bool = False,
           readme: Path | None = None, studies_root: Path | None = None) -> tuple[dict, Path | None]:
    """Draw every figure from ``out_dir``'s records and write ``results_md`` (if set) and README's result blocks
    (if ``readme``); with ``write_run``, also store ``run_info`` (with the figure paths) as ``run.json``. With
    ``studies_root`` (the published ``results/``), the page also reads the other studies' folders there: the payoff
    record (``payoff/``) and the gap tables (``gap/``). Returns (figures, page path)."""
    from anm_torchrl.experiments import plots, readme_blocks, report
    from anm_torchrl.experiments.io import load_results, read_json, write_json
    from anm_torchrl.experiments.records import load_published

    if studies_root is not None:
        results = load_published(studies_root)
    else:  # a run directory: its own records (issue 15's gap tables are records of python -m anm_torchrl.cli.gap)
        results = load_results(out_dir)
        results["optimal_gap_tables"] = {f.stem: read_json(f) for f in sorted(out_dir.glob("optimal_gap_table*.json"))}
        results["records_dir"] = str(out_dir)  # the pages name these records, not the published ones
    figs = plots.make_all(results, out_dir / "figures")
    if write_run:
        run_info["figures"] = {k: os.path.relpath(v, out_dir) if v else None for k, v in figs.items()}
        write_json(out_dir / "run.json", run_info)
    results["run"] = run_info  # the provenance of every record, as written (or about to be)
    md = report.write_results_md(results, figs, results_md, run_info) if results_md else None
    if readme is not None:
        readme_blocks.update_readme(readme, results)
    return figs, md


def by_study(experiments: list[str]) -> dict[str, list[str]]:
    """The experiments grouped by the study folder (``results/<study>/``) their records are published into."""
    from anm_torchrl.experiments.registry import EXPERIMENTS

    out: dict[str, list[str]] = {}
    for name in experiments:
        out.setdefault(EXPERIMENTS[name].study, []).append(name)
    return out


register_help()  # --help lists only this recipe's config groups (recipes/conf/hydra/help/recipe.yaml)


@hydra.main(config_path="conf", config_name="reproduce", version_base="1.3")
def main(cfg: DictConfig) -> dict:
    from hydra.core.hydra_config import HydraConfig

    from anm_torchrl.experiments.publish import check_publish, committed_run, publish
    from anm_torchrl.experiments.records import REPRODUCTION

    t0 = time.perf_counter()
    target, target_md = _abs(cfg.publish_dir), _abs(cfg.publish_md)
    readme = REPO / "README.md" if cfg.publish_readme else None
    if cfg.report_only:  # run nothing: redraw figures and pages from records already written
        if cfg.publish:
            render(target / REPRODUCTION, target_md, committed_run(target / REPRODUCTION), readme=readme,
                   studies_root=target)
            log.info("report only: redrew %s, %s", target, target_md)
            return committed_run(target / REPRODUCTION)
        if cfg.out_dir is None:
            raise SystemExit("reproduce.py: report_only=true needs out_dir=<a run directory> (or publish=true for "
                             "results/)")
        out_dir = _run_dir(cfg)
        from anm_torchrl.training.recipe_errors import user_errors

        with user_errors("reproduce.py", HydraConfig.get().runtime.output_dir):
            if not (out_dir / "run.json").is_file():
                raise FileNotFoundError(f"out_dir={out_dir} holds no run.json: not the folder of a reproduction run")
        run_info = json.loads((out_dir / "run.json").read_text())
        figs, md = render(out_dir, _md(cfg, out_dir), run_info)
        log.info("report only: figures %s, page %s", sorted(figs), md)
        return run_info
    p = OmegaConf.to_container(cfg.preset, resolve=True)
    experiments = list(p.get("experiments", []))
    from anm_torchrl.experiments import registry

    from anm_torchrl.training.config_checks import check_reproduce_config
    from anm_torchrl.training.recipe_errors import defined_keys, refuse_appended_keys, user_errors

    with user_errors("reproduce.py", HydraConfig.get().runtime.output_dir):  # one line, before anything runs
        # a study's options (preset.<study>.reuse, ...) are added with +preset.<...>=, as docs/RESULTS.md shows
        refuse_appended_keys("reproduce.py", HydraConfig.get().overrides.task, allowed=("preset",),
                             defined=defined_keys())
        check_reproduce_config(cfg)
        for name in experiments:  # an unknown name is refused, a count below 1 too
            registry.check(name)
            registry.check_section(name, p.get(name))
        if cfg.publish:
            for study, names in by_study(experiments).items():
                check_publish(target / study, str(p.get("name")), names, bool(cfg.merge), bool(cfg.force))
        earlier = _run_dir(cfg) / "run.json" if cfg.out_dir is not None else None
        if earlier is not None and earlier.is_file() and not cfg.merge:  # its page would mix both runs' records
            left = sorted(set(json.loads(earlier.read_text()).get("experiments", {})) - set(experiments))
            if left:
                raise FileExistsError(f"out_dir={_run_dir(cfg)} holds an earlier run's records of {left}, which this "
                                      "run does not redo; add merge=true to merge into it, or choose another out_dir")
    import torch

    from anm_torchrl.experiments.common import RunContext
    from anm_torchrl.experiments.io import write_json
    from anm_torchrl.provenance import machine_info, versions

    torch.set_num_threads(int(cfg.threads))
    out_dir = _run_dir(cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    surrogates = [dict(s) for s in p.get("surrogates", [])]
    pinn_spec, pinn_logs, pinn_train_s = prepare_pinn(p.get("pinn", {}) or {}, out_dir)
    surrogates = [pinn_spec if s["name"] == "pinn" else s for s in surrogates]
    # claim 2 counts the surrogate's training in CPU seconds (one thread): the PPO wall times it is added to may
    # come from runs on a quieter machine (reused runs), and a loaded machine stretches wall time, not CPU time
    train_s = {} if pinn_train_s is None else {"pinn": pinn_train_s["cpu_s"]}

    run_info = {"name": "run", "status": "ok", "preset": p.get("name"), "command": " ".join(
        ["python recipes/reproduce.py", *sys.argv[1:]]), "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "seeds": {"seed": int(cfg.seed), "ppo_seeds": p.get("seeds")}, "machine": machine_info(),
        "versions": versions(), "surrogate_training": {} if pinn_train_s is None else {"pinn": pinn_train_s}, "config": OmegaConf.to_container(cfg, resolve=True),
        "experiments": {}}
    ctx = RunContext(out_dir=out_dir, surrogates=tuple(surrogates), seed=int(cfg.seed),
                     seeds=tuple(int(s) for s in p.get("seeds", [0])), threads=int(cfg.threads),
                     pinn_logs=tuple(pinn_logs), surrogate_train_s=train_s)
    for name in experiments:
        log.info("experiment %s ...", name)
        rec = run_experiment(name, cfg, ctx)
        rec["meta"].update(machine=run_info["machine"], versions=run_info["versions"])
        write_json(out_dir / f"{name}.json", rec)
        write_tables(rec, out_dir)
        run_info["experiments"][name] = {"status": rec["status"], "reason": rec.get("reason"),
                                         "wall_s": rec["meta"]["wall_s"],
                                         "git_commit": run_info["versions"].get("git_commit")}
        log.info("experiment %s: %s (%.0f s) %s", name, rec["status"], rec["meta"]["wall_s"], rec.get("reason") or "")
    run_info["wall_s"] = wall = time.perf_counter() - t0
    if cfg.merge and cfg.out_dir is not None and (out_dir / "run.json").exists() and not cfg.publish:
        from anm_torchrl.experiments.publish import merge_into_earlier

        run_info = merge_into_earlier(json.loads((out_dir / "run.json").read_text()), run_info)
    figs, md = render(out_dir, _md(cfg, out_dir), run_info, write_run=True)
    log.info("records, figures and %s in %s", md, out_dir)
    if cfg.publish:
        for study, names in by_study(list(run_info["experiments"])).items():
            publish(out_dir, target / study, {**run_info, "experiments": {n: run_info["experiments"][n] for n in names}},
                    merge=bool(cfg.merge))
        render(target / REPRODUCTION, target_md, committed_run(target / REPRODUCTION) or {}, write_run=True,
               readme=readme, studies_root=target)
        log.info("published into %s, %s%s", target, target_md, " and README.md" if readme else "")
    log.info("done in %.0f s: %s", wall, {k: v["status"] for k, v in run_info["experiments"].items()})
    return run_info

if __name__ == "__main__":
    main()
