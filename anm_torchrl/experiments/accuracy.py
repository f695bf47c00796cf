"""R² and MAE of every data-driven surrogate × dataset, in- and cross-dataset (paper Fig. 7).

Nothing is recomputed here: the numbers are those the data-driven training recipe writes (``metrics.json`` in
each trained surrogate's folder, or any JSON given in ``paths``). The reader walks each JSON and collects every
object holding numeric ``r2`` and ``mae``; the key path tells the split and the evaluation dataset
(``generative``/``agent``; absent = the model's own training dataset). Per-output entries are skipped.
Beside each ``metrics.json``, the model's ``surrogate.json`` says what shaped it: the dataset (kind, size, seed,
checksum), the network key and the training budget reached (epochs or boosting rounds, and why training stopped);
the record keeps that per model (``data["models"]``).
"""

from __future__ import annotations

import glob
import json
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.common import RunContext
from anm_torchrl.experiments.io import result

DATASETS = ("generative", "agent")
SKIP = ("per", "per_output", "per_variable", "outputs")


def _walk(obj: Any, path: tuple[str, ...]):
    if isinstance(obj, dict):
        if isinstance(obj.get("r2"), (int, float)) and isinstance(obj.get("mae"), (int, float)):
            yield path, obj
        for k, v in obj.items():
            if str(k) not in SKIP:
                yield from _walk(v, path + (str(k),))


def rows_from_metrics(path: str | Path) -> list[dict[str, Any]]:
    """Rows (model, train_dataset, eval_dataset, split, r2, mae, source) from one metrics JSON."""
    path = Path(path)
    data = json.loads(path.read_text())
    folder = path.parent.name
    kind = data.get("kind") if isinstance(data, dict) else None
    train_ds = data.get("dataset") if isinstance(data, dict) else None
    if kind is None or train_ds is None:
        parts = folder.split("_")
        kind = kind or parts[0]
        train_ds = train_ds or (parts[1] if len(parts) > 1 else None)
    rows = []
    for keys, m in _walk(data, ()):
        # the dataset evaluated on: named inside the entry ({"cross_dataset": {"dataset": "generative", ...}}),
        # else by a key on the path, else the training dataset
        eval_ds = m.get("dataset") if m.get("dataset") in DATASETS else next(
            (k for k in reversed(keys) if k in DATASETS), train_ds)
        model, tds = kind, train_ds
        for k in keys:  # an aggregate file: {"xgb": {"agent": {...}}} or {"xgb_agent": {...}}
            head = k.split("_")
            if head[0] in ("lr", "dt", "rf", "xgb", "dnn", "pinn"):
                model = head[0]
                if len(head) > 1 and head[1] in DATASETS:
                    tds = head[1]
        split = "/".join(k for k in keys if k not in DATASETS and k.split("_")[0] != model) or "test"
        rows.append({"model": model, "train_dataset": tds, "eval_dataset": eval_ds,
                     "cross": eval_ds is not None and tds is not None and eval_ds != tds, "split": split,
                     "r2": float(m["r2"]), "mae": float(m["mae"]), "source": str(path)})
    return rows


def provenance(metrics_path: str | Path) -> dict[str, Any]:
    """What shaped the model whose ``metrics.json`` is at ``metrics_path``: its training dataset (``dataset_meta``:
    kind, size, seed, checksum), ``network_key``, ``seed``, the hyper-parameters ``params`` and the training
    summary (``train_info``: epochs / rounds reached, ``stop``, seconds), read from the ``surrogate.json`` beside it;
    ``{}`` when there is none (a metrics file given alone)."""
    path = Path(metrics_path).parent / "surrogate.json"
    if not path.is_file():
        return {}
    meta = json.loads(path.read_text())
    info = {k: v for k, v in (meta.get("train_info") or {}).items() if k != "params"}
    return {"dataset_meta": meta.get("dataset_meta"), "network_key": (meta.get("simulator") or {}).get("network_key"),
            "seed": meta.get("seed"), "params": meta.get("params"), "train_info": info}


def run(cfg: dict[str, Any], ctx: RunContext) -> dict:
    """cfg keys: ``paths`` (globs of metrics JSON; default ``<artifact home>/surrogates/*/metrics.json``)."""
    from anm_torchrl.paths import artifact_home

    pats = list(cfg.get("paths") or []) or [str(artifact_home() / "surrogates" / "*" / "metrics.json")]
    files = sorted({f for p in pats for f in glob.glob(str(p))})
    rows, errors, models = [], {}, {}
    for f in files:
        try:
            rows += rows_from_metrics(f)
            models[str(Path(f).parent.name)] = provenance(f)
        except (OSError, ValueError) as err:
            errors[f] = str(err)
    if not rows:
        return result("accuracy", "not available",
                      reason=f"no data-driven metrics found (searched {pats}); train them with "
                             "recipes/train_surrogate.py", config=cfg)
    return result("accuracy", "ok" if not errors else "partial", {"rows": rows, "files": files, "errors": errors,
                                                                "models": models},
                  config=cfg)
