"""Training a data-driven surrogate on first use, so ``make_env("xgb", network=<any network>)`` just works.

What :func:`train_default` trains is what ``python recipes/train_surrogate.py network=<n> surrogate=<kind>`` trains
with no other option: the default dataset of that kind (:mod:`anm_torchrl.data.defaults`: 100,000 rows, seed 0,
generated first when missing), the model's default hyper-parameters (``conf/models/default.yaml``) and the terminal
classifier's (``conf/terminal/default.yaml``), seed 0, saved atomically into the default folder. The recipe also
writes its metrics and TensorBoard logs; this writes the model folder only (its ``surrogate.json`` says it was
trained on first use).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from anm_torchrl.data import ensure_dataset, split
from anm_torchrl.data.defaults import DEFAULT_FRACTIONS, DEFAULT_OPTIONS, DEFAULT_SEED, DEFAULT_SIZE
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.surrogates.regressors.fit import fit_regressor
from anm_torchrl.surrogates.regressors.io import save_surrogate
from anm_torchrl.surrogates.terminal import TerminalClassifier

log = logging.getLogger(__name__)


def train_default(kind: str, dataset: str, sim: GridSimulator, path: str | Path, n_jobs: int = 1,
                  progress: bool = True, size: int = DEFAULT_SIZE) -> dict:
    """Train surrogate ``kind`` on ``sim``'s default ``dataset`` and save it to folder ``path``.

    Args:
        size: dataset rows; the default folder takes only the default size (the caller's rule, as the recipe's).

    Returns:
        ``{"dataset_seconds", "fit_seconds", "terminal_seconds", "rows"}``.
    """
    t0 = time.perf_counter()
    td, meta = ensure_dataset(dataset, int(size), DEFAULT_SEED, sim=sim, progress=progress,
                              fractions=DEFAULT_FRACTIONS, **DEFAULT_OPTIONS[dataset])
    t1 = time.perf_counter()
    tr, va = split(td, "train"), split(td, "val")
    sur = fit_regressor(kind, tr, va, sim=sim, n_jobs=n_jobs, seed=DEFAULT_SEED, progress=progress)
    t2 = time.perf_counter()
    clf = TerminalClassifier(sim=sim, n_jobs=n_jobs, seed=DEFAULT_SEED)
    clf.fit(tr.get("state"), tr.get("action"), tr.get("terminated"),
            eval_set=(va.get("state"), va.get("action"), va.get("terminated")), progress=progress)
    sur.classifier = clf
    t3 = time.perf_counter()
    info = {"dataset_seconds": t1 - t0, "fit_seconds": t2 - t1, "terminal_seconds": t3 - t2, "rows": int(size)}
    save_surrogate(sur, path, extra={"dataset": dataset,
                                     "dataset_meta": {k: meta[k] for k in ("kind", "size", "seed", "checksum")},
                                     "trained_on_first_use": info})
    log.info("%s on the %s dataset trained on first use in %.0f s (dataset %.0f s, model %.0f s, terminal "
             "classifier %.0f s) and saved to %s", kind, dataset, t3 - t0, t1 - t0, t2 - t1, t3 - t2, path)
    return info
