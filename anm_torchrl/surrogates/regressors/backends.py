"""The fitted models behind the data-driven surrogates: standardised features (N, F) float64 -> standardised
targets (N, T) float64, each with a file format that cannot run code.

* scikit-learn (``lr``, ``dt``, ``rf``): skops (``skops.io``); only the types skops trusts plus the tree
  structure ``sklearn.tree._tree.Tree`` load; anything else raises before an object is built. Measured on a
  20,000 × 30 → 10 forest (16 trees per output): 21 MB, load 0.32 s (joblib: 18 MB, 0.08 s).
* XGBoost (``xgb``): the booster's own UBJSON format.
* DNN: safetensors through :mod:`anm_torchrl.artifacts` (hash, finite weights), architecture in the metadata.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from anm_torchrl._extras import require
from anm_torchrl.artifacts import ArtifactError, load_tensors, save_tensors
from anm_torchrl.surrogates.regressors.defaults import KINDS
from anm_torchrl.surrogates.terminal import ModelFileError, load_booster

DNN_KIND = "anm_torchrl.dnn"
#: Types skops does not trust by default that a fitted tree model needs (the compiled tree structure).
SKOPS_TRUSTED = ("sklearn.tree._tree.Tree",)


def clone_fit(estimator, x: np.ndarray, y: np.ndarray):
    """A fitted clone of a scikit-learn ``estimator``."""
    clone = require("sklearn.base").clone

    return clone(estimator).fit(x, y)


class Backend:
    """A fitted model mapping standardised features (N, F) float64 to standardised targets (N, T) float64.

    Every subclass has the same ``fit`` and ``load`` signatures (:data:`BACKENDS` dispatches on the kind alone) and
    names its model file in ``FILE``."""

    kind: str
    FILE: str

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def save(self, folder: Path) -> None:
        """Write the model file into ``folder`` (a folder being saved atomically)."""
        raise NotImplementedError


class SklearnBackend(Backend):
    CLASSES = {"lr": "LinearRegression", "dt": "MultiOutputRegressor", "rf": "MultiOutputRegressor"}
    INNER = {"dt": "DecisionTreeRegressor", "rf": "RandomForestRegressor"}

    def __init__(self, kind: str, estimator):
        self.kind, self.estimator = kind, estimator

    FILE = "model.skops"

    @classmethod
    def fit(cls, kind: str, x: torch.Tensor, y: torch.Tensor, xv: torch.Tensor, yv: torch.Tensor, params: dict,
            n_jobs: int, seed: int, progress: bool, log_dir=None) -> tuple["SklearnBackend", dict]:
        """Fit on (x, y) (no early stopping: the validation rows and ``log_dir`` are not used)."""
        require("sklearn")
        import joblib
        from sklearn.ensemble import RandomForestRegressor
        from sklearn.linear_model import LinearRegression
        from sklearn.multioutput import MultiOutputRegressor
        from sklearn.tree import DecisionTreeRegressor

        x, y = x.numpy(), y.numpy()
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

    def save(self, folder: Path) -> None:
        sio = require("skops.io")

        sio.dump(self.estimator, folder / self.FILE)

    @classmethod
    def load(cls, kind: str, folder: Path, n_features: int, n_targets: int, n_jobs: int = 1) -> "SklearnBackend":
        sio = require("skops.io")

        f = folder / cls.FILE
        if not f.is_file():
            raise ModelFileError(f"{kind} model file {f} is missing")
        try:
            untrusted = sio.get_untrusted_types(file=f)
        except Exception as err:  # noqa: BLE001 - any unreadable file is "not a skops file"
            raise ModelFileError(f"{f} is not a readable skops file ({type(err).__name__}: {err})") from err
        unknown = sorted(set(untrusted) - set(SKOPS_TRUSTED))
        if unknown:
            raise ModelFileError(f"{f} holds types that are not trusted, refusing to load it: {unknown}")
        est = sio.load(f, trusted=list(untrusted))
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


class XGBBackend(Backend):
    kind = "xgb"
    FILE = "model.ubj"

    def __init__(self, booster, n_jobs: int):
        self.booster, self.n_jobs = booster, int(n_jobs)

    @classmethod
    def fit(cls, kind: str, x: torch.Tensor, y: torch.Tensor, xv: torch.Tensor, yv: torch.Tensor, params: dict,
            n_jobs: int, seed: int, progress: bool, log_dir=None) -> tuple["XGBBackend", dict]:
        """Boost on (x, y), early-stopped on (xv, yv) (``log_dir`` not used)."""
        from anm_torchrl.surrogates._xgb import train_booster

        x, y, xv, yv = x.numpy(), y.numpy(), xv.numpy(), yv.numpy()
        p = dict(params)
        rounds, early = int(p.pop("num_boost_round")), p.pop("early_stopping_rounds")
        min_delta = float(p.pop("early_stopping_min_delta", 0.0))
        p = {"objective": "reg:squarederror", "eval_metric": "rmse", "tree_method": "hist",
             "multi_strategy": "one_output_per_tree", "nthread": int(n_jobs), "seed": int(seed), **p}
        booster, info = train_booster(p, x, y, xv, yv, rounds, early, progress=progress, desc="xgb",
                                      min_delta=min_delta)
        return cls(booster, n_jobs), info

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        from anm_torchrl.surrogates._xgb import predict

        y = predict(self.booster, x.detach().cpu().to(torch.float32).numpy(), self.n_jobs)
        return torch.as_tensor(np.asarray(y, dtype=np.float64).reshape(x.shape[0], -1), device=x.device)

    def save(self, folder: Path) -> None:
        self.booster.save_model(str(folder / self.FILE))

    @classmethod
    def load(cls, kind: str, folder: Path, n_features: int, n_targets: int, n_jobs: int = 1) -> "XGBBackend":
        f = folder / cls.FILE
        booster = load_booster(f, "xgb model file")
        booster.set_param({"nthread": int(n_jobs)})
        n_out = np.asarray(booster.inplace_predict(np.zeros((1, booster.num_features())))).reshape(1, -1).shape[1]
        if booster.num_features() != n_features or n_out != n_targets:
            raise ModelFileError(f"{f} maps {booster.num_features()} inputs to {n_out} outputs; this state layout "
                                 f"needs {n_features} -> {n_targets}: it was made for another state layout")
        return cls(booster, n_jobs)


class DNNBackend(Backend, torch.nn.Module):
    kind = "dnn"
    FILE = "model.safetensors"

    def __init__(self, mlp):
        torch.nn.Module.__init__(self)
        self.mlp = mlp

    @classmethod
    def fit(cls, kind: str, x: torch.Tensor, y: torch.Tensor, xv: torch.Tensor, yv: torch.Tensor, params: dict,
            n_jobs: int, seed: int, progress: bool, log_dir=None) -> tuple["DNNBackend", dict]:
        """Train the MLP on (x, y), early-stopped on (xv, yv), TensorBoard in ``log_dir`` (``n_jobs``: torch's)."""
        from anm_torchrl.surrogates.dnn import train_mlp

        mlp, info = train_mlp(x, y, xv, yv, params, seed=seed, progress=progress, log_dir=log_dir)
        return cls(mlp), info

    def predict(self, x: torch.Tensor) -> torch.Tensor:
        dev = next(self.mlp.parameters()).device
        with torch.no_grad():
            return self.mlp(x.to(dev, torch.float32)).to(x.device, torch.float64)

    def save(self, folder: Path) -> None:
        save_tensors(folder / self.FILE, self.mlp.state_dict(), {"arch": self.mlp.arch}, DNN_KIND)

    @classmethod
    def load(cls, kind: str, folder: Path, n_features: int, n_targets: int, n_jobs: int = 1) -> "DNNBackend":
        from anm_torchrl.surrogates.dnn import MLP

        f = folder / cls.FILE
        if not f.is_file():
            raise ModelFileError(f"dnn model file {f} is missing")
        tensors, meta = load_tensors(f, DNN_KIND)
        arch = meta.get("arch") or {}
        if arch.get("in_dim") != n_features or arch.get("out_dim") != n_targets:
            raise ModelFileError(f"{f} maps {arch.get('in_dim')} inputs to {arch.get('out_dim')} outputs; this state "
                                 f"layout needs {n_features} -> {n_targets}: it was made for another state layout")
        mlp = MLP(**arch)
        try:
            mlp.load_state_dict(tensors)
        except RuntimeError as err:
            raise ArtifactError(f"{f} weights do not fit its architecture: {err}") from err
        mlp.eval()
        return cls(mlp)


#: the backend class of each data-driven kind: the one dispatch of fitting, loading and file names
BACKENDS: dict[str, type[Backend]] = {k: {"xgb": XGBBackend, "dnn": DNNBackend}.get(k, SklearnBackend)
                                      for k in KINDS}
MODEL_FILES: dict[str, str] = {kind: b.FILE for kind, b in BACKENDS.items()}


def load_backend(kind: str, folder: Path, n_features: int, n_targets: int, n_jobs: int) -> Backend:
    """The fitted model of ``kind`` saved in ``folder`` (already verified against its manifest)."""
    return BACKENDS[kind].load(kind, folder, n_features, n_targets, n_jobs)
