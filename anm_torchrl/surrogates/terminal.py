"""``TerminalClassifier``: gradient boosting that predicts whether a step ends in a terminal state.

In ANM6-Easy a step is terminal when its power flow does not converge (voltage collapse under strongly
negative reactive injections, ≈0.5 % of uniformly random transitions). A regressor cannot learn that from
next-state values, so — as in the paper (§3.1, "a binary classifier based on gradient boosting") — each
data-driven surrogate takes its ``terminated`` output from this classifier, trained on the simulator's
terminations in the same dataset.

Model: ``xgboost`` binary logistic trees on the :class:`~anm_torchrl.surrogates.features.Featurizer` inputs
(state, time of day, action, next-step loads and potentials). Class imbalance: positives are weighted by
``n_negative / n_positive`` (``scale_pos_weight``), early stopping watches the validation area under the
precision–recall curve, and the decision threshold is then chosen on the validation split to maximise F1
(weighting alone makes 0.5 far too eager). Report: accuracy, precision, recall on terminal steps, F1.

API used elsewhere (the PINN chain): ``fit(state, action, terminated, eval_set=...)``,
``predict_terminated(state (N, state_dim) f64, action (N, action_dim) f64) -> (N,) bool``, ``save(dir)``,
``load(dir, sim=...)``.
A saved classifier is an artifact folder (``terminal.json``, ``terminal.ubj``, ``manifest.json``; atomic, hash
checked before reading, :mod:`anm_torchrl.artifacts`); inside a regressor surrogate's folder the surrogate's
manifest covers the same two files. The foresight features read the simulator it is loaded on; ``terminal.json``
records the :func:`~anm_torchrl.grid.identity.network_key` of the network it was trained on, and loading it on
another network raises (as a regressor or PINN file does).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anm_torchrl._extras import require
from anm_torchrl._version import __version__
from anm_torchrl.artifacts import ArtifactError, atomic_folder, verify_manifest, write_manifest
from anm_torchrl.grid.identity import network_key
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.strict_json import json_text
from anm_torchrl.surrogates._xgb import predict as xgb_predict, train_booster
from anm_torchrl.surrogates.conf import load_defaults
from anm_torchrl.surrogates.features import Featurizer

log = logging.getLogger(__name__)

FORMAT = "anm_torchrl.terminal_classifier"
FORMAT_VERSION = 2
META_FILE = "terminal.json"
MODEL_FILE = "terminal.ubj"

KIND = "anm_torchrl.terminal_classifier"  # manifest kind of a stand-alone classifier folder
#: Defaults, one home: ``anm_torchrl/surrogates/conf/terminal/default.yaml`` (documented there).
DEFAULTS: dict[str, Any] = load_defaults("terminal/default")
#: Booster parameters: the fixed objective, then the YAML's (early stopping on validation AUC-PR).
DEFAULT_PARAMS: dict[str, Any] = {"objective": "binary:logistic", "eval_metric": "aucpr", "tree_method": "hist",
                                  **DEFAULTS["params"]}


class ModelFileError(ArtifactError):
    """A model file is missing, of the wrong kind, or was made for another state layout (a ``ValueError``)."""


def classification_metrics(pred: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Accuracy, precision, recall (on terminal steps), F1 and counts for bool tensors (N,)."""
    pred, truth = pred.reshape(-1).bool().cpu(), truth.reshape(-1).bool().cpu()
    tp, fp = int((pred & truth).sum()), int((pred & ~truth).sum())
    fn, tn = int((~pred & truth).sum()), int((~pred & ~truth).sum())
    n = max(tp + fp + fn + tn, 1)
    precision = tp / (tp + fp) if tp + fp else float("nan")
    recall = tp / (tp + fn) if tp + fn else float("nan")
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else float("nan")
    return {"accuracy": (tp + tn) / n, "precision": precision, "recall": recall, "f1": f1,
            "n": tp + fp + fn + tn, "n_terminal": tp + fn, "tp": tp, "fp": fp, "fn": fn, "tn": tn}


def layout_of(sim: GridSimulator, featurizer: Featurizer) -> dict[str, Any]:
    """The state/action layout a model depends on (compared when loading)."""
    return {"state_dim": sim.state_dim, "action_dim": sim.action_dim, "n_time": sim.n_time,
            "features": list(featurizer.names)}


class TerminalClassifier:
    """Predicts ``terminated`` from ``(state, action)``; see the module docstring.

    Args:
        sim: simulator giving the layout and time series (default ANM6-Easy).
        foresight: use next-step loads and potentials as inputs.
        params: xgboost parameters overriding :data:`DEFAULT_PARAMS`.
        num_boost_round: maximum boosting rounds.
        early_stopping_rounds: rounds without validation improvement before stopping.
        threshold: ``"f1"`` (tune on the validation set) or a probability in (0, 1).
        n_jobs: xgboost threads (training and prediction).
        seed: xgboost seed.
    """

    def __init__(self, sim: GridSimulator | None = None, foresight: bool = True, params: dict | None = None,
                 num_boost_round: int = DEFAULTS["num_boost_round"],
                 early_stopping_rounds: int = DEFAULTS["early_stopping_rounds"],
                 threshold: str | float = DEFAULTS["threshold"], n_jobs: int = 1, seed: int = 0):
        self.sim = sim if sim is not None else network_simulator(ANM6_EASY)
        self.featurizer = Featurizer(self.sim, foresight=foresight)
        self.params = {**DEFAULT_PARAMS, **(params or {})}
        self.num_boost_round, self.early_stopping_rounds = int(num_boost_round), int(early_stopping_rounds)
        self.threshold_rule = threshold
        self.threshold = 0.5 if threshold == "f1" else float(threshold)
        self.n_jobs, self.seed = int(n_jobs), int(seed)
        self.booster = None
        self.constant: bool | None = None  # set when the training data had a single class
        self.info: dict[str, Any] = {}

    # ----------------------------------------------------------------------------------------------- fit
    def _x(self, state: torch.Tensor, action: torch.Tensor) -> np.ndarray:
        return self.featurizer(state.detach().cpu(), action.detach().cpu()).numpy()

    def fit(self, state: torch.Tensor, action: torch.Tensor, terminated: torch.Tensor,
            eval_set: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
            progress: bool = False) -> "TerminalClassifier":
        """Train on ``state`` (N, state_dim), ``action`` (N, action_dim) MW/MVAr and ``terminated`` (N,) or (N, 1) bool.

        ``eval_set = (state, action, terminated)`` enables early stopping and threshold tuning.
        """
        y = terminated.reshape(-1).bool().cpu().numpy()
        n_pos, n_neg = int(y.sum()), int((~y).sum())
        self.info = {"n_train": int(y.size), "n_train_terminal": n_pos}
        if n_pos == 0 or n_neg == 0:
            self.constant, self.booster = bool(n_pos > 0), None
            log.warning("terminal classifier: the training data has a single class (%d terminal of %d); it will "
                        "always predict %s", n_pos, y.size, self.constant)
            return self
        self.constant = None
        params = {**self.params, "scale_pos_weight": n_neg / n_pos, "nthread": self.n_jobs, "seed": self.seed}
        xv = yv = None
        if eval_set is not None:
            xv = self._x(eval_set[0], eval_set[1])
            yv = eval_set[2].reshape(-1).bool().cpu().numpy()
            if yv.sum() == 0:  # AUC-PR is undefined without positives: stop on log-loss instead
                params["eval_metric"] = "logloss"
        self.booster, info = train_booster(params, self._x(state, action), y.astype(np.float32), xv,
                                           None if yv is None else yv.astype(np.float32), self.num_boost_round,
                                           self.early_stopping_rounds, progress=progress, desc="terminal")
        self.info.update(info)
        if self.threshold_rule == "f1" and yv is not None and yv.sum() > 0:
            self.threshold = _best_f1_threshold(self._proba_np(xv), yv)
        self.info["threshold"] = self.threshold
        return self

    # ------------------------------------------------------------------------------------------- predict
    def _proba_np(self, x: np.ndarray) -> np.ndarray:
        if self.booster is None:
            if self.constant is None:
                raise RuntimeError("TerminalClassifier is not fitted: call fit() or TerminalClassifier.load()")
            return np.full(x.shape[0], 1.0 if self.constant else 0.0)
        return xgb_predict(self.booster, x, self.n_jobs)

    def predict_proba(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Probability (N,) float64 that the step from ``state`` (N, state_dim) under ``action`` (N, action_dim) is
        terminal."""
        p = self._proba_np(self._x(state, action))
        return torch.as_tensor(np.asarray(p, dtype=np.float64), device=state.device)

    def predict_terminated(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Terminal decision (N,) bool for ``state`` (N, state_dim) float64 and ``action`` (N, action_dim) float64
        MW/MVAr."""
        return self.predict_proba(state, action) >= self.threshold

    def evaluate(self, state: torch.Tensor, action: torch.Tensor, terminated: torch.Tensor) -> dict[str, float]:
        """Classification metrics (:func:`classification_metrics`) on a labelled batch."""
        return classification_metrics(self.predict_terminated(state, action), terminated)

    # ------------------------------------------------------------------------------------------ save/load
    def save(self, path: str | os.PathLike, overwrite: bool = True) -> Path:
        """Write the classifier as its own artifact folder ``path`` (atomic, with a manifest)."""
        with atomic_folder(path, overwrite=overwrite, kind=KIND) as tmp:
            self.write_files(tmp)
            write_manifest(tmp, KIND)
        return Path(path)

    def write_files(self, folder: str | os.PathLike) -> None:
        """Write ``terminal.json`` (+ ``terminal.ubj``, the booster) into ``folder`` (being saved atomically)."""
        folder = Path(folder)
        if self.booster is None and self.constant is None:
            raise RuntimeError("cannot save an unfitted TerminalClassifier")
        meta = {
            "format": FORMAT, "format_version": FORMAT_VERSION, "package_version": __version__,
            "network_key": network_key(self.sim),
            "layout": layout_of(self.sim, self.featurizer), "foresight": self.featurizer.foresight,
            "params": self.params, "num_boost_round": self.num_boost_round,
            "early_stopping_rounds": self.early_stopping_rounds, "threshold_rule": self.threshold_rule,
            "threshold": self.threshold, "constant": self.constant, "n_jobs": self.n_jobs, "seed": self.seed,
            "info": self.info,
        }
        if self.booster is not None:
            self.booster.save_model(str(folder / MODEL_FILE))
        (folder / META_FILE).write_text(json_text(meta, indent=2))

    @classmethod
    def load(cls, path: str | os.PathLike, sim: GridSimulator | None = None, n_jobs: int | None = None
             ) -> "TerminalClassifier":
        """Load a classifier folder saved by :meth:`save` (its manifest is checked first) to run on ``sim``.

        Raises:
            ArtifactError: no manifest, a file changed since the save, or another kind of folder.
            ModelFileError: another kind of file, or a model made for another state layout.
        """
        verify_manifest(path, KIND)
        return cls.read_files(path, sim=sim, n_jobs=n_jobs)

    @classmethod
    def read_files(cls, path: str | os.PathLike, sim: GridSimulator | None = None, n_jobs: int | None = None
                   ) -> "TerminalClassifier":
        """Rebuild a classifier from the files :meth:`write_files` wrote (the caller verified the folder) to run on
        ``sim`` (None: ANM6-Easy).

        Raises:
            ModelFileError: another kind of file, a model trained on another network than ``sim``'s (or written
                before the network was recorded), or one made for another state layout.
        """
        path = Path(path)
        meta = read_meta(path / META_FILE, "terminal classifier", FORMAT, FORMAT_VERSION, "retrain the classifier")
        sim = sim if sim is not None else network_simulator(ANM6_EASY)
        check_network(meta, sim, path / META_FILE)
        clf = cls(sim=sim, foresight=meta["foresight"], params=meta["params"],
                  num_boost_round=meta["num_boost_round"], early_stopping_rounds=meta["early_stopping_rounds"],
                  threshold=meta["threshold_rule"], n_jobs=meta["n_jobs"] if n_jobs is None else n_jobs,
                  seed=meta["seed"])
        check_layout(meta.get("layout"), layout_of(clf.sim, clf.featurizer), path / META_FILE)
        clf.threshold, clf.constant, clf.info = float(meta["threshold"]), meta["constant"], meta.get("info", {})
        if clf.constant is None:
            f = path / MODEL_FILE
            booster = load_booster(f, "terminal classifier model")
            if booster.num_features() != clf.featurizer.n_features:
                raise ModelFileError(f"{f} expects {booster.num_features()} inputs, the layout has "
                                     f"{clf.featurizer.n_features}; it was made for another state layout")
            booster.set_param({"nthread": clf.n_jobs})
            clf.booster = booster
        return clf


def check_network(meta: dict, sim: GridSimulator, where) -> None:
    """Raise :class:`ModelFileError` (a ``ValueError``) unless the classifier described by ``meta`` was trained on
    ``sim``'s network: the same layout on another network would load, then predict that network's terminations."""
    have, want = meta.get("network_key"), network_key(sim)
    if have is None:
        raise ModelFileError(f"{where} records no network key: it predates the network check and cannot be told "
                             f"apart from a classifier of another network; retrain the classifier (network "
                             f"{want!r})")
    if have != want:
        raise ModelFileError(f"{where} was trained on network {have!r}, the simulator is network {want!r}: train a "
                             f"terminal classifier for this network")


def check_layout(have: dict | None, want: dict, where) -> None:
    """Raise :class:`ModelFileError` naming the differing entries if a stored layout differs from ``want``."""
    if not isinstance(have, dict):
        raise ModelFileError(f"{where} records no state layout; it is not a model of this package")
    diff = sorted(k for k in want if have.get(k) != want[k])
    if diff:
        detail = "; ".join(f"{k}: file {have.get(k)!r} vs now {want[k]!r}" for k in diff)
        raise ModelFileError(f"{where} was made for another state layout ({detail}); retrain it")


def load_booster(f: Path, what: str):
    """An ``xgboost.Booster`` from ``f``; :class:`ModelFileError` if the file is missing or not an xgboost model."""
    xgb = require("xgboost")

    if not f.is_file():
        raise ModelFileError(f"{what} {f} is missing")
    try:
        return xgb.Booster(model_file=str(f))
    except xgb.core.XGBoostError as err:
        raise ModelFileError(f"{f} is not an xgboost model ({str(err).splitlines()[0]})") from err


def read_meta(f: Path, what: str, fmt: str, version: int, retrain: str) -> dict:
    """The JSON description ``f`` of a saved model, checked to be of format ``fmt`` and version ``version``.

    Raises:
        ModelFileError: missing or unreadable file, another kind of file, or another format version (the
            message ends with ``retrain``, what to do about it).
    """
    if not f.is_file():
        raise ModelFileError(f"no {what} at {f.parent}: {f.name} is missing")
    try:
        meta = json.loads(f.read_text())
    except (OSError, ValueError) as err:
        raise ModelFileError(f"{f} is not a readable {what} description ({err})") from err
    if not isinstance(meta, dict):
        raise ModelFileError(f"{f} is not a {what} description")
    if meta.get("format") != fmt:
        raise ModelFileError(f"{f} is not a {what} (format {meta.get('format')!r}, expected {fmt!r})")
    if meta.get("format_version") != version:
        raise ModelFileError(f"{f} has format version {meta.get('format_version')}, this package reads "
                             f"{version}; {retrain}")
    return meta


def _best_f1_threshold(proba: np.ndarray, truth: np.ndarray) -> float:
    """The probability threshold (predict ``p >= t``) that maximises F1 on a validation set."""
    order = np.argsort(-proba, kind="stable")
    p, y = proba[order], truth[order].astype(np.int64)
    tp = np.cumsum(y)
    fp = np.cumsum(1 - y)
    fn = y.sum() - tp
    f1 = 2 * tp / np.maximum(2 * tp + fp + fn, 1)
    # only cut between distinct probabilities
    last = np.r_[p[1:] != p[:-1], True]
    f1 = np.where(last, f1, -1)
    best = int(np.argmax(f1))
    return float(p[best])
