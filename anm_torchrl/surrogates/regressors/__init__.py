"""Data-driven surrogates of ANM6-Easy: Linear Regression, Decision Tree, Random Forest, XGBoost and a DNN.

Each model maps ``(state, action)`` — through the :class:`~anm_torchrl.surrogates.features.Featurizer`
(state, time of day, action, next-step loads and potentials) — to the physics-decided next-state entries
(P and Q of slack, PV, wind and storage, storage SoC) and the reward (``features.target_layout``), all
standardised with the training split's mean and standard deviation. Terminal rows are left out of the
regression (their "next state" is gym-anm's zero vector); the terminal decision comes from a
:class:`~anm_torchrl.surrogates.terminal.TerminalClassifier` trained on the same dataset and saved alongside.

Split by job: :mod:`.defaults` (names, file layout, hyper-parameters), :mod:`.backends` (the fitted models and
their code-free file formats), :mod:`.module` (:class:`RegressorSurrogate`, the ``SurrogateEnv`` model: one
batched ``predict`` of the regressor and one of the classifier per env step), :mod:`.fit`, :mod:`.metrics`,
:mod:`.io` (atomic, hash-checked folders) and :mod:`.loaders` (the registry's loaders).
"""

from anm_torchrl.surrogates.regressors.backends import BACKENDS, MODEL_FILES
from anm_torchrl.surrogates.regressors.defaults import (DATASETS, DEFAULT_PARAMS, FORMAT, FORMAT_VERSION, KINDS,
                                                        META_FILE, train_command)
from anm_torchrl.surrogates.regressors.fit import fit_regressor, regression_rows, targets_of
from anm_torchrl.surrogates.regressors.io import load_surrogate_folder, save_surrogate
from anm_torchrl.surrogates.regressors.loaders import load_regressor_surrogate
from anm_torchrl.surrogates.regressors.metrics import evaluate_surrogate, regression_metrics
from anm_torchrl.surrogates.regressors.module import RegressorSurrogate

__all__ = ["BACKENDS", "DATASETS", "DEFAULT_PARAMS", "FORMAT", "FORMAT_VERSION", "KINDS", "META_FILE", "MODEL_FILES",
           "RegressorSurrogate", "evaluate_surrogate", "fit_regressor", "load_regressor_surrogate",
           "load_surrogate_folder", "regression_metrics", "regression_rows", "save_surrogate", "targets_of",
           "train_command"]
