"""``make_env``: the one factory users call for the true simulator, gym-anm itself, or any surrogate."""

from __future__ import annotations

from pathlib import Path

import torch
from torchrl.envs import DoubleToFloat, EnvBase, SerialEnv, StepCounter, TransformedEnv

from anm_torchrl.envs import ANM6Env, SurrogateEnv
from anm_torchrl.paths import artifact_home
from anm_torchrl.surrogates.registry import load_surrogate

GYM_ANM_ID = "gym_anm:ANM6Easy-v0"


def make_gym_anm_env(num_envs: int = 1, device="cpu", seed: int | None = None) -> EnvBase:
    """The original gym-anm 2.0.1 package through TorchRL's ``GymEnv`` (float32 observation/action/reward).

    Slow (≈25 steps/s per env, cvxpy + scipy); ``num_envs > 1`` steps them serially in one process.
    """
    from torchrl.envs import GymEnv

    try:
        import gym_anm  # noqa: F401
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ImportError("surrogate='gym_anm' needs the gym-anm package: pip install gym-anm==2.0.1") from err
    make = lambda: GymEnv(GYM_ANM_ID, device=device)  # noqa: E731
    env = make() if num_envs == 1 else SerialEnv(num_envs, make)
    env = TransformedEnv(env, DoubleToFloat())
    if seed is not None:
        env.set_seed(seed)
    return env


def load_surrogate_in_home(name: str, **kwargs):
    """:func:`load_surrogate`, with a file-system error under the artifact home re-raised naming
    ``ANM_TORCHRL_HOME`` (a surrogate trained on first use is cached there).

    Raises:
        OSError: of the original type, saying which variable to set; other errors pass unchanged.
    """
    try:
        return load_surrogate(name, **kwargs)
    except OSError as err:
        home = artifact_home()
        where = Path(str(err.filename)) if err.filename else None
        if where is None or not (where == home or home in where.parents):
            raise
        raise type(err)(f"cannot write the artifact cache {home} ({err.strerror or err}: {where}); "
                        f"set ANM_TORCHRL_HOME to a writable folder, or pass path=") from err


def make_env(surrogate: str = "none", num_envs: int = 1, max_steps: int | None = None, device="cpu",
             seed: int | None = None, action_mode: str = "raise", init: str | None = None,
             **surrogate_kwargs) -> EnvBase:
    """Build a batched env of ``num_envs`` grids.

    Args:
        surrogate: ``"none"`` (the true simulator ``ANM6Env``), ``"gym_anm"`` (the original package, slow), or a
            registered surrogate (``pinn``, ``xgb``, ``rf``, ``dt``, ``lr``, ``dnn``; see
            :func:`anm_torchrl.surrogates.available_surrogates`).
        num_envs: batch size.
        max_steps: episode time limit (``StepCounter``: ``truncated``/``done`` at that step); gym-anm has
            none, the literature evaluates over 3,000 steps.
        device: torch device.
        seed: reset seed.
        action_mode: ``"raise"`` or ``"clip"`` for actions outside the box.
        init: reset distribution (``"gym_anm"``, ``"intended"``, ``"uniform"``); default ``"gym_anm"`` for the
            true simulator and ``"uniform"`` for surrogates.
        **surrogate_kwargs: passed to the surrogate's loader (e.g. ``dataset="agent"``, ``path=...``).
    """
    if surrogate in (None, "none"):
        env = ANM6Env(num_envs, device=device, seed=seed, action_mode=action_mode, init=init or "gym_anm")
    elif surrogate == "gym_anm":
        env = make_gym_anm_env(num_envs, device=device, seed=seed)
    else:
        model = load_surrogate_in_home(surrogate, device=device, **surrogate_kwargs)
        env = SurrogateEnv(model, num_envs, device=device, seed=seed, action_mode=action_mode,
                           init=init or "uniform")
    if surrogate in (None, "none", "gym_anm") and surrogate_kwargs:
        raise ValueError(f"surrogate={surrogate!r} takes no surrogate options, got {sorted(surrogate_kwargs)}")
    if max_steps is not None:
        if isinstance(env, TransformedEnv):  # gym_anm: extend its transforms rather than nest envs
            env.append_transform(StepCounter(int(max_steps)))
        else:
            env = TransformedEnv(env, StepCounter(int(max_steps)))
    return env
