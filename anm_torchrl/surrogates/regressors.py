"""Data-driven surrogates of ANM6-Easy: Linear Regression, Decision Tree, Random Forest, XGBoost and a DNN.

Each model maps ``(state, action)`` — through the :class:`~anm_torchrl.surrogates.features.Featurizer`
(state, time of day, action, next-step loads and potentials) — to the physics-decided next-state entries
(P and Q of slack, PV, wind and storage, storage SoC) and the reward (``features.target_layout``), all
standardised with the training split's mean and standard deviation. Terminal rows are left out of the
regression (their "next state" is gym-anm's zero vector); the terminal decision comes from a
:class:`~anm_torchrl.surrogates.terminal.TerminalClassifier` trained on the same dataset and saved alongside.

Hyper-parameters (:data:`DEFAULT_PARAMS`; override with ``models.<kind>.<key>=...`` in
``recipes/conf/train_surrogate.yaml``), sized for a 2-core CPU and ~80,000 training rows:

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

A trained surrogate is a folder (default ``anm_torchrl.paths.surrogate_dir(kind, dataset)``)::

    surrogate.json        format marker/version, kind, dataset, state layout, scalers, parameters, training info
    model.joblib          lr / dt / rf: {"format", "kind", "estimator"} (a pickle: load only files you trust)
    model.ubj             xgb: the booster          model.pt   dnn: weights and architecture
    terminal.json/.ubj    the terminal classifier
    metrics.json          R² / MAE on the held-out splits, classifier metrics (written by the recipe)

:class:`RegressorSurrogate` is the ``TensorDictModuleBase`` that ``SurrogateEnv`` runs: one batched
``predict`` of the regressor and one of the classifier per env step, whatever the number of envs.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tqdm.auto import tqdm

import anm_torchrl
from anm_torchrl.grid.simulator import GridSimulator, anm6_easy_simulator
from anm_torchrl.paths import surrogate_dir
from anm_torchrl.surrogates.features import Featurizer, target_layout
from anm_torchrl.surrogates.terminal import ModelFileError, TerminalClassifier, check_layout, load_booster, read_meta

log = logging.getLogger(__name__)

KINDS = ("lr", "dt", "rf", "xgb", "dnn")
DATASETS = ("generative", "agent")
FORMAT = "anm_torchrl.regressor_surrogate"
FORMAT_VERSION = 1
META_FILE = "surrogate.json"
MODEL_FILES = {"lr": "model.joblib", "dt": "model.joblib", "rf": "model.joblib", "xgb": "model.ubj", "dnn": "model.pt"}

DEFAULT_PARAMS: dict[str, dict[str, Any]] = {
    "lr": {},
    "dt": {"max_depth": None, "min_samples_leaf": 3},
    "rf": {"n_estimators": 16, "max_samples": 0.5, "max_features": 0.5, "min_samples_leaf": 8, "max_depth": None},
    "xgb": {"num_boost_round": 1000, "early_stopping_rounds": 30, "early_stopping_min_delta": 2e-4, "max_depth": 8,
            "eta": 0.2, "subsample": 0.8, "colsample_bytree": 0.8, "min_child_weight": 1.0, "max_bin": 256},
    "dnn": {},  # anm_torchrl.surrogates.dnn.DEFAULT_PARAMS
}


def train_command(kind: str, dataset: str, path: str | os.PathLike | None = None) -> str:
    """The command that trains surrogate ``kind`` on ``dataset`` (into ``path`` if not the default)."""
    cmd = f"python recipes/train_surrogate.py surrogate={kind} surrogate.dataset={dataset}"
    return cmd if path is None else f"{cmd} surrogate.path={path}"


# ======================================================================================== regressor backends
def clone_fit(estimator, x: np.ndarray, y: np.ndarray):
    """A fitted clone of a scikit-learn ``estimator``."""
    from sklearn.base import clone

    return clone(estimator).fit(x, y)


class _Backend:
    """A fitted model mapping standardised features (N, F) float64 to standardised targets (N, T) float64."""

    kind: str

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def save(self, path: Path) -> None:
        raise NotImplementedError


class _SklearnBackend(_Backend):
    CLASSES = {"lr": "LinearRegression", "dt": "MultiOutputRegressor", "rf": "MultiOutputRegressor"}
    INNER = {"dt": "DecisionTreeRegressor", "rf": "RandomForestRegressor"}

    def __init__(self, kind: str, estimator):
        self.kind, self.estimator = kind, estimator

    @classmethod
    def fit(cls, kind: str, x: np.ndarray, y: np.ndarray, params: dict, n_jobs: int, seed: int,
            progress: bool) -> tuple["_SklearnBackend", dict]:
        import joblib
        from sklearn.ensemble import RandomForestRegressor
        from sklearn.linear_model import LinearRegression
        from sklearn.multioutput import MultiOutputRegressor
        from sklearn.tree import DecisionTreeRegressor

        info: dict[str, Any] = {}
        if kind == "lr":
            return cls(kind, LinearRegression(**params).fit(x, y)), info
        # Trees: one per output. A single multi-output tree splits on the summed error of all ten outputs and
        # fits each of them much worse (R² 0.88 vs 0.99 for a decision tree on the generative data).
        if kind == "dt":
            inner = DecisionTreeRegressor(random_state=seed, **params)
        else:
            inner = RandomForestRegressor(random_state=seed, n_jobs=n_jobs, **params)
        est = MultiOutputRegressor(inner)
        outputs = tqdm(range(y.shape[1]), desc=kind, unit="output", disable=not progress, leave=False)
        if kind == "dt" and n_jobs > 1:  # trees release the GIL: fit outputs on threads, no worker processes
            est.estimators_ = joblib.Parallel(n_jobs=n_jobs, prefer="threads")(
                joblib.delayed(clone_fit)(inner, x, y[:, j]) for j in outputs)
        else:  # forests use their own n_jobs threads
            with joblib.parallel_config(backend="threading"):
                est.estimators_ = [clone_fit(inner, x, y[:, j]) for j in outputs]
        est.n_features_in_ = x.shape[1]
        for e in est.estimators_:
            if hasattr(e, "n_jobs"):
                e.set_params(n_jobs=1)  # batch-1 inference is faster without a thread pool
        if kind == "dt":
            info = {"n_leaves": [int(e.get_n_leaves()) for e in est.estimators_]}
        else:
            info = {"n_leaves_mean": [float(np.mean([t.get_n_leaves() for t in e.estimators_]))
                                      for e in est.estimators_]}
        return cls(kind, est), info

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        y = self.estimator.predict(x.detach().cpu().numpy())
        return torch.as_tensor(np.asarray(y, dtype=np.float64).reshape(x.shape[0], -1), device=x.device)

    def save(self, path: Path) -> None:
        import joblib

        joblib.dump({"format": FORMAT, "kind": self.kind, "estimator": self.estimator}, path / MODEL_FILES[self.kind])

    @classmethod
    def load(cls, kind: str, path: Path, n_features: int, n_targets: int) -> "_SklearnBackend":
        import joblib

        f = path / MODEL_FILES[kind]
        if not f.is_file():
            raise ModelFileError(f"{kind} model file {f} is missing")
        try:
            obj = joblib.load(f)
        except Exception as err:  # noqa: BLE001 - unpickling can fail in many ways
            raise ModelFileError(f"{f} is not a readable {kind} model ({type(err).__name__}: {err})") from err
        if not isinstance(obj, dict) or obj.get("format") != FORMAT:
            raise ModelFileError(f"{f} is not an anm_torchrl surrogate model file")
        if obj.get("kind") != kind:
            raise ModelFileError(f"{f} holds a {obj.get('kind')!r} model, not {kind!r}")
        est = obj.get("estimator")
        if type(est).__name__ != cls.CLASSES[kind]:
            raise ModelFileError(f"{f} holds a {type(est).__name__}, expected a {cls.CLASSES[kind]} for {kind!r}")
        if kind in cls.INNER:
            inner = {type(e).__name__ for e in getattr(est, "estimators_", [])}
            if inner != {cls.INNER[kind]}:
                raise ModelFileError(f"{f} holds {sorted(inner)} per output, expected {cls.INNER[kind]} for {kind!r}")
            got_t = len(est.estimators_)
        else:
            got_t = est.coef_.shape[0] if getattr(est, "coef_", None) is not None and est.coef_.ndim == 2 else None
        got_f = getattr(est, "n_features_in_", None)
        if got_f != n_features or got_t != n_targets:
            raise ModelFileError(f"{f} maps {got_f} inputs to {got_t} outputs; this state layout needs "
                                 f"{n_features} -> {n_targets}: it was made for another state layout")
        return cls(kind, est)


class _XGBBackend(_Backend):
    kind = "xgb"

    def __init__(self, booster):
        self.booster = booster

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, xv: np.ndarray, yv: np.ndarray, params: dict, n_jobs: int,
            seed: int, progress: bool) -> tuple["_XGBBackend", dict]:
        from anm_torchrl.surrogates._xgb import train_booster

        p = dict(params)
        rounds, early = int(p.pop("num_boost_round")), p.pop("early_stopping_rounds")
        min_delta = float(p.pop("early_stopping_min_delta", 0.0))
        p = {"objective": "reg:squarederror", "eval_metric": "rmse", "tree_method": "hist",
             "multi_strategy": "one_output_per_tree", "nthread": int(n_jobs), "seed": int(seed), **p}
        booster, info = train_booster(p, x, y, xv, yv, rounds, early, progress=progress, desc="xgb",
                                      min_delta=min_delta)
        return cls(booster), info

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        # xgboost compares features in float32: casting here gives the same trees, and is faster
        y = self.booster.inplace_predict(x.detach().cpu().to(torch.float32).numpy(), validate_features=False)
        return torch.as_tensor(np.asarray(y, dtype=np.float64).reshape(x.shape[0], -1), device=x.device)

    def save(self, path: Path) -> None:
        self.booster.save_model(str(path / MODEL_FILES["xgb"]))

    @classmethod
    def load(cls, path: Path, n_features: int, n_targets: int, n_jobs: int) -> "_XGBBackend":
        f = path / MODEL_FILES["xgb"]
        booster = load_booster(f, "xgb model file")
        booster.set_param({"nthread": int(n_jobs)})
        n_out = np.asarray(booster.inplace_predict(np.zeros((1, booster.num_features())))).reshape(1, -1).shape[1]
        if booster.num_features() != n_features or n_out != n_targets:
            raise ModelFileError(f"{f} maps {booster.num_features()} inputs to {n_out} outputs; this state layout "
                                 f"needs {n_features} -> {n_targets}: it was made for another state layout")
        return cls(booster)


class _DNNBackend(_Backend, torch.nn.Module):
    kind = "dnn"

    def __init__(self, mlp):
        torch.nn.Module.__init__(self)
        self.mlp = mlp

    @classmethod
    def fit(cls, x: torch.Tensor, y: torch.Tensor, xv: torch.Tensor, yv: torch.Tensor, params: dict, seed: int,
            progress: bool, log_dir) -> tuple["_DNNBackend", dict]:
        from anm_torchrl.surrogates.dnn import train_mlp

        mlp, info = train_mlp(x, y, xv, yv, params, seed=seed, progress=progress, log_dir=log_dir)
        return cls(mlp), info

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        dev = next(self.mlp.parameters()).device
        with torch.no_grad():
            return self.mlp(x.to(dev, torch.float32)).to(x.device, torch.float64)

    def save(self, path: Path) -> None:
        torch.save({"format": FORMAT, "kind": "dnn", "arch": self.mlp.arch,
                    "state_dict": {k: v.cpu() for k, v in self.mlp.state_dict().items()}}, path / MODEL_FILES["dnn"])

    @classmethod
    def load(cls, path: Path, n_features: int, n_targets: int) -> "_DNNBackend":
        from anm_torchrl.surrogates.dnn import MLP

        f = path / MODEL_FILES["dnn"]
        if not f.is_file():
            raise ModelFileError(f"dnn model file {f} is missing")
        try:
            obj = torch.load(f, map_location="cpu", weights_only=True)
        except Exception as err:  # noqa: BLE001
            raise ModelFileError(f"{f} is not a readable torch file ({type(err).__name__}: {err})") from err
        if not isinstance(obj, dict) or obj.get("format") != FORMAT or obj.get("kind") != "dnn":
            raise ModelFileError(f"{f} is not an anm_torchrl dnn model file")
        arch = obj["arch"]
        if arch.get("in_dim") != n_features or arch.get("out_dim") != n_targets:
            raise ModelFileError(f"{f} maps {arch.get('in_dim')} inputs to {arch.get('out_dim')} outputs; this state "
                                 f"layout needs {n_features} -> {n_targets}: it was made for another state layout")
        mlp = MLP(**arch)
        try:
            mlp.load_state_dict(obj["state_dict"])
        except RuntimeError as err:
            raise ModelFileError(f"{f} weights do not fit its architecture: {err}") from err
        mlp.eval()
        return cls(mlp)


# ============================================================================================ the surrogate
class RegressorSurrogate(TensorDictModuleBase):
    """A trained regressor + terminal classifier as a ``SurrogateEnv`` transition model.

    Reads ``"state"`` (N, 18) and ``"action"`` (N, 6) (any float dtype, MW/MVAr), writes ``"next_state"``
    (N, 18) float64 (predicted physics entries; the other entries are copied from ``state`` and overwritten by
    the env), ``"reward"`` (N, 1) float64 and ``"terminated"`` (N, 1) bool. With ``clip`` the predicted
    entries are clamped to the state's observation bounds (the slack excepted, whose bounds gym-anm does not
    enforce) and the reward to gym-anm's clipping range [−(c₁ + c₂), c₁].

    Build one with :func:`fit_regressor` or :meth:`load`.
    """

    in_keys = ["state", "action"]
    out_keys = ["next_state", "reward", "terminated"]

    def __init__(self, kind: str, backend: _Backend, sim: GridSimulator, featurizer: Featurizer,
                 x_mean: torch.Tensor, x_std: torch.Tensor, y_mean: torch.Tensor, y_std: torch.Tensor,
                 classifier: TerminalClassifier | None = None, clip: bool = True, meta: dict | None = None):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        self.kind, self.backend, self.sim, self.featurizer = kind, backend, sim, featurizer
        self.classifier, self.clip, self.meta = classifier, bool(clip), dict(meta or {})
        idx, names = target_layout(sim)
        self.target_names = names
        self.register_buffer("target_index", torch.tensor(idx, dtype=torch.long))
        for name, t in (("x_mean", x_mean), ("x_std", x_std), ("y_mean", y_mean), ("y_std", y_std)):
            self.register_buffer(name, torch.as_tensor(t, dtype=torch.float64).clone())
        low, high = sim.state_bounds()
        low, high = low[idx].clone().to(torch.float64), high[idx].clone().to(torch.float64)
        slack = [k for k, i in enumerate(idx) if i - sim.state_slices()["dev_p"].start in sim.slack_ids
                 or i - sim.state_slices()["dev_q"].start in sim.slack_ids]
        low[slack], high[slack] = -torch.inf, torch.inf
        c1, c2 = sim.costs_clipping
        self.register_buffer("y_low", torch.cat([low, low.new_tensor([-(c1 + c2)])]))
        self.register_buffer("y_high", torch.cat([high, high.new_tensor([c1])]))

    # ---------------------------------------------------------------------------------------------- predict
    def features(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Standardised inputs (N, F) float64."""
        x = self.featurizer(state.to(torch.float64).cpu(), action.to(torch.float64).cpu()).to(self.x_mean.device)
        return (x - self.x_mean) / self.x_std

    def predict_targets(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Predicted targets (N, T) float64 in their units (``target_names``: MW, MVAr, MWh, then reward)."""
        y = self.backend.predict(self.features(state, action)) * self.y_std + self.y_mean
        if self.clip:
            y = torch.maximum(torch.minimum(y, self.y_high), self.y_low)
        return y

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get("state").to(torch.float64)
        action = tensordict.get("action").to(torch.float64)
        y = self.predict_targets(state, action).to(state.device)
        next_state = state.clone()
        next_state[:, self.target_index.to(state.device)] = y[:, :-1]
        if self.classifier is None:
            raise RuntimeError(f"{self.kind} surrogate has no terminal classifier; retrain it "
                               f"({train_command(self.kind, self.meta.get('dataset', 'generative'))})")
        terminated = self.classifier.predict_terminated(state, action).reshape(-1, 1).to(state.device)
        tensordict.set("next_state", next_state)
        tensordict.set("reward", y[:, -1:])
        tensordict.set("terminated", terminated)
        return tensordict

    # ------------------------------------------------------------------------------------------- save/load
    def layout(self) -> dict[str, Any]:
        """The state/action layout this surrogate was trained for (checked on load)."""
        return {"state_dim": self.sim.state_dim, "action_dim": self.sim.action_dim, "n_time": self.sim.n_time,
                "features": list(self.featurizer.names), "targets": list(self.target_names),
                "target_index": self.target_index.tolist()}

    def save(self, path: str | os.PathLike, extra: dict | None = None) -> Path:
        """Write the model, its description and its classifier into folder ``path``."""
        from anm_torchrl.data.storage import simulator_settings

        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        for f in set(MODEL_FILES.values()) - {MODEL_FILES[self.kind]}:  # no stale model of another kind
            if (path / f).exists():
                (path / f).unlink()
        self.backend.save(path)
        if self.classifier is not None:
            self.classifier.save(path)
        meta = {**self.meta, **(extra or {}), "format": FORMAT, "format_version": FORMAT_VERSION, "kind": self.kind,
                "package_version": anm_torchrl.__version__, "layout": self.layout(),
                "foresight": self.featurizer.foresight, "clip": self.clip,
                "simulator": simulator_settings(self.sim),
                "scalers": {k: getattr(self, k).cpu().tolist() for k in ("x_mean", "x_std", "y_mean", "y_std")}}
        (path / META_FILE).write_text(json.dumps(meta, indent=2))
        self.meta = meta
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, kind: str | None = None, device="cpu", sim: GridSimulator | None = None,
             n_jobs: int = 1) -> "RegressorSurrogate":
        """Load a surrogate saved by :meth:`save`.

        Args:
            path: the surrogate folder.
            kind: when given, the folder must hold a surrogate of this kind.
            device: torch device of the module (the DNN runs there; tree models predict on the CPU).
            sim: the simulator (default ANM6-Easy); its layout must match the stored one.
            n_jobs: threads for xgboost prediction.

        Raises:
            ModelFileError: missing or unreadable files, a model of another kind, or another state layout.
        """
        from anm_torchrl.data.storage import simulator_fingerprint

        path = Path(path)
        meta = read_meta(path / META_FILE, "data-driven surrogate", FORMAT, FORMAT_VERSION, "retrain it")
        stored = meta.get("kind")
        if stored not in KINDS:
            raise ModelFileError(f"{path / META_FILE} names an unknown surrogate kind {stored!r}")
        if kind is not None and stored != kind:
            retrain = train_command(kind, meta.get("dataset", "generative"))
            raise ModelFileError(f"{path} holds a {stored!r} surrogate, not {kind!r}: load it with "
                                 f"surrogate={stored} or train a {kind!r} one ({retrain})")
        sim = sim if sim is not None else anm6_easy_simulator()
        featurizer = Featurizer(sim, foresight=meta.get("foresight", True))
        idx, names = target_layout(sim)
        want = {"state_dim": sim.state_dim, "action_dim": sim.action_dim, "n_time": sim.n_time,
                "features": list(featurizer.names), "targets": names, "target_index": idx}
        check_layout(meta.get("layout"), want, path / META_FILE)
        fp = meta.get("simulator", {}).get("fingerprint")
        if fp != simulator_fingerprint(sim):
            log.warning("%s was trained on a simulator with another fingerprint (%s vs %s): its predictions may be "
                        "stale", path, fp, simulator_fingerprint(sim))
        nf, nt = featurizer.n_features, len(names)
        if stored == "xgb":
            backend: _Backend = _XGBBackend.load(path, nf, nt, n_jobs)
        elif stored == "dnn":
            backend = _DNNBackend.load(path, nf, nt)
        else:
            backend = _SklearnBackend.load(stored, path, nf, nt)
        sc = meta.get("scalers", {})
        try:
            scalers = {k: torch.tensor(sc[k], dtype=torch.float64) for k in ("x_mean", "x_std", "y_mean", "y_std")}
        except (KeyError, TypeError, ValueError) as err:
            raise ModelFileError(f"{path / META_FILE} has no valid scalers ({err})") from err
        if scalers["x_mean"].shape != (nf,) or scalers["y_mean"].shape != (nt,):
            raise ModelFileError(f"{path / META_FILE} scalers do not fit the state layout")
        classifier = TerminalClassifier.load(path, sim=sim, n_jobs=n_jobs)
        out = cls(stored, backend, sim, featurizer, classifier=classifier, clip=meta.get("clip", True), meta=meta,
                  **scalers)
        return out.to(device)


# ================================================================================================ training
def regression_rows(td: TensorDictBase) -> TensorDictBase:
    """The non-terminal rows of a dataset split (terminal rows have gym-anm's zero next state)."""
    return td[~td.get("terminated").reshape(-1).bool()]


def targets_of(td: TensorDictBase, sim: GridSimulator) -> torch.Tensor:
    """Ground-truth targets (N, T) float64 of dataset rows: next-state physics entries, then the reward."""
    idx, _ = target_layout(sim)
    return torch.cat([td.get("next_state")[:, idx], td.get("reward").reshape(-1, 1)], 1).to(torch.float64)


def fit_regressor(kind: str, train: TensorDictBase, val: TensorDictBase, sim: GridSimulator | None = None,
                  params: dict | None = None, foresight: bool = True, clip: bool = True, n_jobs: int = 1,
                  seed: int = 0, progress: bool = False, log_dir: str | os.PathLike | None = None
                  ) -> RegressorSurrogate:
    """Train surrogate ``kind`` on dataset rows ``train`` (validation rows ``val`` for early stopping).

    Terminal rows are dropped. ``params`` override :data:`DEFAULT_PARAMS` ``[kind]``. The returned surrogate has
    no classifier yet: set ``surrogate.classifier`` (a fitted :class:`TerminalClassifier`).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    sim = sim if sim is not None else anm6_easy_simulator()
    featurizer = Featurizer(sim, foresight=foresight)
    tr, va = regression_rows(train), regression_rows(val)
    x = featurizer(tr.get("state"), tr.get("action"))
    y = targets_of(tr, sim)
    x_mean, x_std = x.mean(0), x.std(0)
    y_mean, y_std = y.mean(0), y.std(0)
    x_std = torch.where(x_std > 1e-12, x_std, torch.ones_like(x_std))
    y_std = torch.where(y_std > 1e-12, y_std, torch.ones_like(y_std))
    xs, ys = (x - x_mean) / x_std, (y - y_mean) / y_std
    xv = (featurizer(va.get("state"), va.get("action")) - x_mean) / x_std
    yv = (targets_of(va, sim) - y_mean) / y_std
    p = {**DEFAULT_PARAMS[kind], **(params or {})}
    start = time.perf_counter()
    if kind == "xgb":
        backend, info = _XGBBackend.fit(xs.numpy(), ys.numpy(), xv.numpy(), yv.numpy(), p, n_jobs, seed, progress)
    elif kind == "dnn":
        backend, info = _DNNBackend.fit(xs, ys, xv, yv, p, seed, progress, log_dir)
    else:
        backend, info = _SklearnBackend.fit(kind, xs.numpy(), ys.numpy(), p, n_jobs, seed, progress)
    info = {**info, "train_seconds": time.perf_counter() - start, "n_train": int(xs.shape[0]),
            "n_val": int(xv.shape[0])}
    log.info("%s trained in %.1f s on %d rows", kind, info["train_seconds"], xs.shape[0])
    meta = {"params": {k: v for k, v in p.items()}, "train_info": _jsonable(info), "seed": int(seed)}
    return RegressorSurrogate(kind, backend, sim, featurizer, x_mean, x_std, y_mean, y_std, clip=clip, meta=meta)


# ================================================================================================= metrics
def regression_metrics(pred: torch.Tensor, truth: torch.Tensor, names: list[str]) -> dict[str, Any]:
    """R² and MAE per output and overall (the unweighted mean over outputs).

    ``mae`` is in each output's unit (MW, MVAr, MWh, reward units — all of similar magnitude here); ``nmae``
    divides each MAE by that output's standard deviation on ``truth``.
    """
    pred, truth = pred.to(torch.float64).cpu(), truth.to(torch.float64).cpu()
    err = pred - truth
    sse = (err ** 2).sum(0)
    sst = ((truth - truth.mean(0)) ** 2).sum(0)
    r2 = torch.where(sst > 0, 1 - sse / sst, torch.full_like(sse, float("nan")))
    mae = err.abs().mean(0)
    std = truth.std(0)
    nmae = torch.where(std > 0, mae / std, torch.full_like(mae, float("nan")))
    per = {n: {"r2": float(r2[i]), "mae": float(mae[i])} for i, n in enumerate(names)}
    return {"r2": float(np.nanmean(r2.numpy())), "mae": float(mae.mean()), "nmae": float(np.nanmean(nmae.numpy())),
            "n": int(truth.shape[0]), "per_output": per}


def evaluate_surrogate(surrogate: RegressorSurrogate, td: TensorDictBase, batch: int = 65536) -> dict[str, Any]:
    """Regression metrics on the non-terminal rows of ``td`` and classifier metrics on all its rows."""
    rows = regression_rows(td)
    preds = [surrogate.predict_targets(rows.get("state")[i:i + batch], rows.get("action")[i:i + batch])
             for i in range(0, rows.shape[0], batch)]
    out = regression_metrics(torch.cat(preds) if preds else torch.zeros(0, len(surrogate.target_names)),
                             targets_of(rows, surrogate.sim), surrogate.target_names)
    if surrogate.classifier is not None:
        out["terminal"] = surrogate.classifier.evaluate(td.get("state"), td.get("action"), td.get("terminated"))
    return out


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


# ================================================================================================= loaders
def load_regressor_surrogate(kind: str, device="cpu", dataset: str = "generative",
                             path: str | os.PathLike | None = None) -> RegressorSurrogate:
    """Load trained surrogate ``kind`` for ``dataset`` from ``path`` (default ``surrogate_dir(kind, dataset)``).

    Raises:
        FileNotFoundError: nothing trained there; the message gives the command that trains it.
        ModelFileError: a corrupted model, a model of another kind, or one for another state layout.
    """
    if dataset not in DATASETS:
        raise ValueError(f"dataset must be one of {DATASETS}, got {dataset!r}")
    default = path is None
    p = surrogate_dir(kind, dataset) if default else Path(path)
    if not (p / META_FILE).is_file():
        raise FileNotFoundError(f"no trained {kind!r} surrogate for the {dataset!r} dataset at {p}; train it with: "
                                f"{train_command(kind, dataset, None if default else p)}")
    sur = RegressorSurrogate.load(p, kind=kind, device=device)
    stored = sur.meta.get("dataset")
    if stored != dataset:
        if default:
            raise ModelFileError(f"{p} holds a surrogate trained on the {stored!r} dataset, expected {dataset!r}; "
                                 f"retrain it: {train_command(kind, dataset)}")
        log.warning("%s was trained on the %r dataset (dataset=%r was asked for)", p, stored, dataset)
    return sur


def load_lr(device="cpu", dataset: str = "generative", path: str | os.PathLike | None = None) -> RegressorSurrogate:
    """The Linear Regression surrogate (see :func:`load_regressor_surrogate`)."""
    return load_regressor_surrogate("lr", device, dataset, path)


def load_dt(device="cpu", dataset: str = "generative", path: str | os.PathLike | None = None) -> RegressorSurrogate:
    """The Decision Tree surrogate (see :func:`load_regressor_surrogate`)."""
    return load_regressor_surrogate("dt", device, dataset, path)


def load_rf(device="cpu", dataset: str = "generative", path: str | os.PathLike | None = None) -> RegressorSurrogate:
    """The Random Forest surrogate (see :func:`load_regressor_surrogate`)."""
    return load_regressor_surrogate("rf", device, dataset, path)


def load_xgb(device="cpu", dataset: str = "generative", path: str | os.PathLike | None = None) -> RegressorSurrogate:
    """The XGBoost surrogate (see :func:`load_regressor_surrogate`)."""
    return load_regressor_surrogate("xgb", device, dataset, path)


def load_dnn(device="cpu", dataset: str = "generative", path: str | os.PathLike | None = None) -> RegressorSurrogate:
    """The DNN surrogate (see :func:`load_regressor_surrogate`)."""
    return load_regressor_surrogate("dnn", device, dataset, path)
