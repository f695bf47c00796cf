"""Training pipeline of the data-driven surrogates behind ``recipes/train_surrogate.py`` (its steps and folders are
described there): datasets, the terminal classifier (cached per dataset checksum, options and seed), the regressor,
its evaluation in- and cross-dataset, one atomic save with a manifest.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from anm_torchrl.strict_json import json_text
from anm_torchrl.surrogates.regressors.requests import check_default_slot, check_request, check_train_config

log = logging.getLogger("train_surrogate")


def load_datasets(cfg: DictConfig, sim, make_cfg: DictConfig, default_size: int) -> dict:
    """``{kind: (td, meta)}`` for both datasets (generated first when missing and allowed, with ``make_cfg``'s
    per-kind options and split ``fractions``: the dataset recipe's config), with the default slot's size rule
    checked on each dataset a model is trained on (an explicit data folder may be small too; ``default_size``: the
    default ``data.size``)."""
    from anm_torchrl.data import available_datasets, ensure_dataset, load_dataset

    out = {}
    for kind in available_datasets():
        options = dict(make_cfg[kind]) if kind in make_cfg else {}
        start = time.perf_counter()
        if cfg.data.get(kind):  # an explicit folder: used as it is (its own size and seed), never generated
            out[kind] = load_dataset(cfg.data.get(kind), kind=kind, sim=sim, verify=bool(cfg.data.verify))
        else:
            out[kind] = ensure_dataset(kind, int(cfg.data.size), int(cfg.data.seed),
                                       generate_missing=bool(cfg.data.generate_missing), sim=sim,
                                       progress=bool(cfg.progress), verify=bool(cfg.data.verify),
                                       fractions=tuple(make_cfg.fractions), **options)
        log.info("%s dataset ready (%d rows, %d terminal) in %.1f s", kind, out[kind][0].shape[0],
                 out[kind][1].get("n_terminal", -1), time.perf_counter() - start)
    path = None if cfg.all else cfg.surrogate.get("path")
    for kind in (available_datasets() if cfg.all else [cfg.surrogate.dataset]):
        check_default_slot(out[kind][1]["size"], path, bool(cfg.overwrite_cache), default_size)
    return out


def fit_terminal(cfg: DictConfig, dataset: str, data: dict, sim):
    """The terminal classifier for ``dataset``: the cached one for this dataset checksum, options and seed if
    ``terminal.reuse``, else trained (and cached under that key)."""
    from anm_torchrl.data import split
    from anm_torchrl.paths import surrogate_dir
    from anm_torchrl.artifacts import ArtifactError
    from anm_torchrl.surrogates.terminal import TerminalClassifier

    td, meta = data[dataset]
    options = OmegaConf.to_container(cfg.terminal, resolve=True)
    options.pop("reuse", None)
    key = hashlib.sha256(json.dumps([meta["checksum"], options, bool(cfg.foresight), int(cfg.seed)],
                                    sort_keys=True).encode()).hexdigest()[:16]
    cache = surrogate_dir("terminal", dataset) / key  # one folder per (data, options): runs never evict each other
    if cfg.terminal.reuse and (cache / "terminal.json").is_file():
        try:
            clf = TerminalClassifier.load(cache, sim=sim, n_jobs=int(cfg.n_jobs))
            if clf.info.get("cache_key") == key:
                log.info("terminal classifier for %s reused from %s", dataset, cache)
                return clf
        except ArtifactError as err:
            log.warning("cached terminal classifier at %s is unusable (%s); retraining", cache, err)
    tr, va = split(td, "train"), split(td, "val")
    start = time.perf_counter()
    clf = TerminalClassifier(sim=sim, foresight=bool(cfg.foresight), params=options["params"],
                             num_boost_round=options["num_boost_round"],
                             early_stopping_rounds=options["early_stopping_rounds"], threshold=options["threshold"],
                             n_jobs=int(cfg.n_jobs), seed=int(cfg.seed))
    clf.fit(tr.get("state"), tr.get("action"), tr.get("terminated"),
            eval_set=(va.get("state"), va.get("action"), va.get("terminated")), progress=bool(cfg.progress))
    clf.info.update(cache_key=key, train_seconds=time.perf_counter() - start, dataset=dataset)
    log.info("terminal classifier for %s trained in %.1f s (threshold %.3f)", dataset, clf.info["train_seconds"],
             clf.threshold)
    if cfg.terminal.reuse:
        clf.save(cache)
    return clf


def train_one(cfg: DictConfig, name: str, dataset: str, path: str | None, data: dict, sim) -> dict:
    """Train, save and evaluate surrogate ``name`` on ``dataset``; returns its metrics."""
    from anm_torchrl.data import for_network, split
    from anm_torchrl.paths import surrogate_dir
    from anm_torchrl.surrogates.regressors import DATASETS, evaluate_surrogate, fit_regressor, save_surrogate

    check_request(name, dataset)
    out = Path(path) if path else for_network(surrogate_dir(name, dataset), sim)
    total = time.perf_counter()
    td, meta = data[dataset]
    clf = fit_terminal(cfg, dataset, data, sim)
    params = OmegaConf.to_container(cfg.models[name], resolve=True) if name in cfg.models else {}
    log.info("training %s on the %s dataset -> %s", name, dataset, out)
    tb = Path(tempfile.mkdtemp(prefix=f"{name}_tb_")) if name == "dnn" else None
    sur = fit_regressor(name, split(td, "train"), split(td, "val"), sim=sim, params=params,
                        foresight=bool(cfg.foresight), clip=bool(cfg.clip), n_jobs=int(cfg.n_jobs),
                        seed=int(cfg.seed), progress=bool(cfg.progress), log_dir=None if tb is None else str(tb))
    sur.classifier = clf
    other = [d for d in DATASETS if d != dataset][0]
    metrics = {"kind": name, "dataset": dataset,
               "in_dataset": evaluate_surrogate(sur, split(td, "test")),
               "cross_dataset": {"dataset": other, **evaluate_surrogate(sur, split(data[other][0], "test"))},
               "val": evaluate_surrogate(sur, split(td, "val")),
               "train_seconds": sur.meta["train_info"]["train_seconds"],
               "terminal_train_seconds": clf.info.get("train_seconds")}
    metrics["total_seconds"] = time.perf_counter() - total
    job_cfg = OmegaConf.to_container(cfg, resolve=True)
    job_cfg["surrogate"] = {"name": name, "dataset": dataset, "path": path}
    files = {"metrics.json": json_text(metrics, indent=2), "config.yaml": OmegaConf.to_yaml(OmegaConf.create(job_cfg)),
             **({"tb": tb} if tb is not None else {})}
    try:
        save_surrogate(sur, out, extra={"dataset": dataset,
                                          "dataset_meta": {k: meta[k] for k in ("kind", "size", "seed", "checksum")},
                                          "metrics": {"in_dataset_r2": metrics["in_dataset"]["r2"],
                                                      "cross_dataset_r2": metrics["cross_dataset"]["r2"]}},
                      files=files)
    finally:
        if tb is not None:
            shutil.rmtree(tb, ignore_errors=True)
    m, c = metrics["in_dataset"], metrics["cross_dataset"]
    log.info("%s/%s: R² %.4f MAE %.4f (test, same dataset) | R² %.4f MAE %.4f (test, %s) | terminal acc %.4f "
             "recall %.3f | %.1f s", name, dataset, m["r2"], m["mae"], c["r2"], c["mae"], other,
             m["terminal"]["accuracy"], m["terminal"]["recall"], metrics["total_seconds"])
    return metrics


def summary_table(results: list[dict]) -> str:
    """A Markdown table of R²/MAE in- and cross-dataset and the classifier's accuracy/recall."""
    lines = ["| model | trained on | R² (same) | MAE (same) | R² (other) | MAE (other) | terminal acc. "
             "| terminal recall | train s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        m, c = r["in_dataset"], r["cross_dataset"]
        lines.append(f"| {r['kind']} | {r['dataset']} | {m['r2']:.4f} | {m['mae']:.3f} | {c['r2']:.4f} "
                     f"| {c['mae']:.3f} | {m['terminal']['accuracy']:.4f} | {m['terminal']['recall']:.3f} "
                     f"| {r['train_seconds']:.1f} |")
    return "\n".join(lines)


def check_train_request(cfg: DictConfig, default_size: int):
    """:func:`~.requests.check_train_config`, then the network, returned as its simulator.

    Raises:
        ValueError: naming the offending key or table."""
    from anm_torchrl.networks import simulator as network_simulator

    check_train_config(cfg, default_size)
    return network_simulator(cfg.network)


def train_surrogates(cfg: DictConfig, make_cfg: DictConfig, default_size: int, sim=None,
                     data: dict | None = None) -> list[dict]:
    """Train what ``cfg`` (``recipes/conf/train_surrogate.yaml``) asks for: one surrogate, or all ten with
    ``all=true``; returns the metrics. ``make_cfg``: the dataset recipe's config (options of missing datasets);
    ``default_size``: the default ``data.size``, below which a model never replaces the default one unless
    ``overwrite_cache``; ``sim``: the network's simulator as :func:`check_train_request` returned it (None: the
    checks run here); ``data``: :func:`load_datasets`'s (None: loaded here)."""
    from anm_torchrl.artifacts import atomic_write
    from anm_torchrl.data import for_network
    from anm_torchrl.paths import artifact_home
    from anm_torchrl.surrogates.regressors import DATASETS, KINDS

    torch.set_num_threads(int(cfg.threads))
    if sim is None:  # fail before loading or generating data
        sim = check_train_request(cfg, default_size)
    start = time.perf_counter()
    if data is None:
        data = load_datasets(cfg, sim, make_cfg, default_size)
    if cfg.all:
        jobs = [(k, d) for d in DATASETS for k in KINDS]
        results = [train_one(cfg, k, d, None, data, sim)
                   for k, d in tqdm(jobs, desc="surrogates", unit="model", disable=not cfg.progress)]
        table = summary_table(results)
        out = for_network(artifact_home() / "surrogates", sim)
        atomic_write(out / "summary.json", json_text(results, indent=2).encode())
        atomic_write(out / "summary.md", (table + "\n").encode())
        log.info("all surrogates trained in %.1f s; summary in %s\n%s", time.perf_counter() - start,
                 out / "summary.md", table)
        return results
    dataset = cfg.surrogate.get("dataset")
    return [train_one(cfg, cfg.surrogate.name, dataset, cfg.surrogate.get("path"), data, sim)]
