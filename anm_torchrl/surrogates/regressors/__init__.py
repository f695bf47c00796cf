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
Names load on first use (:mod:`anm_torchrl.lazy`): :mod:`.defaults` and :mod:`.requests` import without torch.
"""

from anm_torchrl.lazy import lazy_exports

_HOMES = {
    **dict.fromkeys(["BACKENDS", "MODEL_FILES"], "backends"),
    **dict.fromkeys(["DATASETS", "DEFAULT_PARAMS", "FORMAT", "FORMAT_VERSION", "KINDS", "META_FILE", "train_command"],
                    "defaults"),
    **dict.fromkeys(["fit_regressor", "regression_rows", "targets_of"], "fit"),
    **dict.fromkeys(["load_surrogate_folder", "save_surrogate"], "io"),
    "load_regressor_surrogate": "loaders",
    **dict.fromkeys(["evaluate_surrogate", "regression_metrics"], "metrics"),
    "RegressorSurrogate": "module",
}
__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
