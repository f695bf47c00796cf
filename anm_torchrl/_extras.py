"""Optional dependencies: import one, or fail with the ``pip install`` line of the extra that provides it.

The core install runs the simulator, the PINN surrogate and PPO (``python recipes/ppo.py surrogate=pinn``);
everything else sits behind an extra of ``pyproject.toml``. :data:`EXTRAS` maps every module imported behind an
extra to that extra, and ``tests/test_extras.py`` checks it against ``pyproject.toml``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: top-level module name -> (extra of pyproject.toml, what needs it).
EXTRAS: dict[str, tuple[str, str]] = {
    "casadi": ("optimum", "the AC optimum and AC-MPC baselines (policy=optimal|acmpc)"),
    "qpsolvers": ("mpc", "the DC-OPF MPC baseline (policy=mpc_perfect|mpc_constant)"),
    "osqp": ("mpc", "the DC-OPF MPC baseline"),
    "clarabel": ("mpc", "the DC-OPF MPC baseline"),
    "sklearn": ("surrogates", "the data-driven surrogates (surrogate=lr|dt|rf|xgb|dnn) and their datasets"),
    "xgboost": ("surrogates", "the XGBoost surrogate and the terminal classifier"),
    "skops": ("surrogates", "saved scikit-learn surrogates"),
    "pandapower": ("feeders", "importing feeders from pandapower / SimBench"),
    "simbench": ("feeders", "importing SimBench feeders"),
    "pandas": ("feeders", "importing feeders from pandapower / SimBench"),
    "joblib": ("surrogates", "the data-driven surrogates"),
    "stable_baselines3": ("sb3", "the Stable-Baselines3 adapter (anm_torchrl.gym.sb3)"),
    "gym_anm": ("gym-anm", "the original gym-anm package (env=gym_anm, surrogate=gym_anm, parity checks)"),
}


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message names the extra that provides it."""


def install_hint(extra: str) -> str:
    """The command that installs ``extra`` from a clone (editable) — the form README's install section uses."""
    return f"pip install -e '.[{extra}]'"


def require(module: str, extra: str | None = None, what: str | None = None) -> ModuleType:
    """``importlib.import_module(module)``, or :class:`MissingExtraError` naming the extra to install.

    Args:
        module: dotted module name, e.g. ``"casadi"`` or ``"skops.io"``; its top-level package is looked up in
            :data:`EXTRAS` when ``extra`` / ``what`` are not given.
        extra: the ``pyproject.toml`` extra that provides it.
        what: what needs it, for the message.

    Raises:
        MissingExtraError: the module (or a package it imports) is missing; chained to the original error.
        KeyError: ``extra`` not given and ``module``'s package is not in :data:`EXTRAS` (a programming error).
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        top = module.split(".")[0]
        known_extra, known_what = EXTRAS[top] if extra is None else EXTRAS.get(top, (extra, "this feature"))
        extra, what = extra or known_extra, what or known_what
        raise MissingExtraError(f"{what} needs the optional package {top!r} (missing: {e.name!r}); install the "
                                f"{extra!r} extra: {install_hint(extra)}  (or pip install -e '.[all]')") from e
