"""Names, file layout and default hyper-parameters of the data-driven surrogates.

Hyper-parameters (:data:`DEFAULT_PARAMS`, one home: ``anm_torchrl/surrogates/conf/models/default.yaml``; override
with ``models.<kind>.<key>=...`` in ``recipes/train_surrogate.py``), sized for a 2-core CPU and ~80,000 training
rows:

=====  ==========================================================================================================
kind   model
=====  ==========================================================================================================
lr     ``sklearn.linear_model.LinearRegression`` (ordinary least squares, all outputs at once).
dt     one ``DecisionTreeRegressor`` per output (``MultiOutputRegressor``), ``min_samples_leaf=3``, unbounded
       depth. (A single multi-output tree splits on the summed error of all outputs: R² 0.88 instead of 0.99.)
rf     one ``RandomForestRegressor`` per output, 16 trees each on a 50 % bootstrap, 50 % of the features per
       split, ``min_samples_leaf=8`` (≈1 min on 2 cores, ≈60 MB on disk per dataset); ``n_jobs`` threads.
xgb    ``xgboost`` multi-output regression (one tree per output per round), depth 8, learning rate 0.2,
       0.8 row/column subsampling, 256-bin histograms, up to 1,000 rounds with early stopping after 30
       rounds without a validation-RMSE gain above 2e-4 (standardised units; only the best rounds are kept).
       Learning rate 0.1 reaches a slightly lower error (R² 0.9988 vs 0.998) in 4× the time.
dnn    torch MLP, see :mod:`anm_torchrl.surrogates.dnn` (3×256 SiLU, AdamW, early stopping, TensorBoard).
=====  ==========================================================================================================

A trained surrogate is a folder (default ``anm_torchrl.paths.surrogate_dir(kind, dataset)``), saved atomically
with a ``manifest.json`` (:mod:`anm_torchrl.artifacts`) checked before anything in it is read::

    surrogate.json        format marker/version, kind, dataset, state layout, network key, scalers, parameters
    model.skops           lr / dt / rf: the estimator in skops format (no pickle: only trusted types load)
    model.ubj             xgb: the booster (XGBoost's own format)
    model.safetensors     dnn: weights, architecture in the metadata
    terminal.json/.ubj    the terminal classifier
    metrics.json, config.yaml, tb/   written by the recipe, inside the same atomic save
    manifest.json         SHA-256 of every file above
"""

from __future__ import annotations

import os
from typing import Any

from anm_torchrl.data.registry import available_datasets
from anm_torchrl.surrogates.conf import load_defaults

#: the kinds this module fits and loads (those with a backend; the registry's data-driven entries load them)
KINDS: tuple[str, ...] = ("lr", "dt", "rf", "xgb", "dnn")  # the model of each: .backends.BACKENDS
DATASETS: tuple[str, ...] = available_datasets()
FORMAT = "anm_torchrl.regressor_surrogate"
FORMAT_VERSION = 2
META_FILE = "surrogate.json"
DEFAULT_PARAMS: dict[str, dict[str, Any]] = load_defaults("models/default")


def train_command(kind: str, dataset: str, sim, path: str | os.PathLike | None = None) -> str:
    """The command that trains surrogate ``kind`` on ``dataset`` (into ``path`` if not the default) for ``sim``'s
    network (a :class:`GridSimulator`; a network other than ANM6-Easy is named by a placeholder: the simulator
    does not know its name)."""
    from anm_torchrl.networks.resolve import is_anm6

    network = "" if is_anm6(sim) else " network=<its name>"
    cmd = f"python recipes/train_surrogate.py{network} surrogate={kind} surrogate.dataset={dataset}"
    return cmd if path is None else f"{cmd} surrogate.path={path}"
