"""``make_env``: the one factory users call for the true simulator, gym-anm itself, or any surrogate."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from torchrl.envs import DoubleToFloat, EnvBase, SerialEnv, StepCounter, TransformedEnv

from anm_torchrl._extras import require
from anm_torchrl.console import plain_torchrl_console
from anm_torchrl.envs import ANM6Env, ANMEnv, SurrogateEnv
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.training.config_checks import TRUE_SIMULATORS, check_gym_anm_options, gym_anm_only
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.paths import artifact_home
from anm_torchrl.surrogates.registry import load_surrogate

plain_torchrl_console()  # torchrl is imported above: no ANSI colours in a redirected run's output

GYM_ANM_ID = "gym_anm:ANM6Easy-v0"


def make_gym_anm_env(num_envs: int = 1, device="cpu", seed: int | None = None) -> EnvBase:
    """The original gym-anm 2.0.1 package through TorchRL's ``GymEnv`` (float32 observation/action/reward).

    Slow (≈25 steps/s per env, cvxpy + scipy); ``num_envs > 1`` steps them serially in one process.
    """
    from torchrl.envs import GymEnv

    require("gym_anm", what="surrogate=gym_anm")
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


ANM6 = ANM6_EASY


def network_arguments(network: str | dict | None = None, load_p=None, gen_p_max=None) -> dict | None:
    """``ANMEnv``'s network arguments for a registered network name or a gym-anm network dict.

    Args:
        network: a name of :func:`anm_torchrl.networks.list_networks`, a gym-anm network dict, or None (ANM6-Easy).
        load_p: (T, n_load) MW; required with a dict, optional with a name (replaces the registered profile).
        gen_p_max: (T, n_gen) MW; as ``load_p``.

    Returns:
        ``{"network", "load_p", "gen_p_max"}`` (plus the registered ``delta_t``, ``gamma``, ``lamb``,
        ``costs_clipping`` for a name), or None for ANM6-Easy with its own profiles (the ``ANM6Env`` preset).

    Raises:
        ValueError: an unknown name, a dict without both profiles, or another type.
    """
    if (network is None or network == ANM6) and load_p is None and gen_p_max is None:
        return None
    if network is None or isinstance(network, str):
        from anm_torchrl.networks import get_network

        case = get_network(ANM6 if network is None else network)
        return {"network": case.network, "load_p": case.load_p if load_p is None else load_p,
                "gen_p_max": case.gen_p_max if gen_p_max is None else gen_p_max, "delta_t": case.delta_t,
                "gamma": case.gamma, "lamb": case.lamb, "costs_clipping": case.costs_clipping}
    if isinstance(network, dict):
        if load_p is None or gen_p_max is None:
            raise ValueError("a network dict needs load_p= (T, n_load) MW and gen_p_max= (T, n_gen) MW profiles")
        return {"network": network, "load_p": load_p, "gen_p_max": gen_p_max}
    raise ValueError(f"network must be a registered name, a gym-anm network dict or None; got {type(network).__name__}")


def make_true_env(num_envs: int = 1, device="cpu", seed: int | None = None, action_mode: str = "raise",
                  init: str | None = None, network: str | dict | None = None, load_p=None,
                  gen_p_max=None) -> ANMEnv:
    """The true simulator of a network (:func:`network_arguments`): the ``ANM6Env`` preset for ANM6-Easy (default
    ``init="gym_anm"``, gym-anm's initial distribution), else ``ANMEnv`` (default ``init="uniform"``)."""
    kwargs = network_arguments(network, load_p, gen_p_max)
    if kwargs is None:
        return ANM6Env(num_envs, device=device, seed=seed, action_mode=action_mode, init=init or "gym_anm")
    return ANMEnv(**kwargs, num_envs=num_envs, seed=seed, device=device, action_mode=action_mode,
                  init=init or "uniform")


class StaggeredStepCounter(StepCounter):
    """``StepCounter`` whose full resets (every env at once: no ``_reset`` mask) start each env's count at a uniform
    0..max_steps-1, drawn from its own seeded generator: the first episodes end after 1..max_steps steps, so later
    resets (partial, from 0) spread over the collected batches instead of falling on all envs at once (then one
    batch in ``max_steps / steps per batch`` holds every env's first steps, the others none)."""

    def __init__(self, max_steps: int, seed: int | None = None):
        super().__init__(int(max_steps))
        self._generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    def _reset(self, tensordict, tensordict_reset):
        full = tensordict is None or all(tensordict.get(key, None) is None for key in self.reset_keys)
        tensordict_reset = super()._reset(tensordict, tensordict_reset)
        if full:
            for key in self.step_count_keys:
                count = tensordict_reset.get(key)
                offset = torch.randint(0, self.max_steps, count.shape, generator=self._generator)
                tensordict_reset.set(key, offset.to(device=count.device, dtype=count.dtype))
        return tensordict_reset


def make_env(surrogate: str = "none", num_envs: int = 1, max_steps: int | None = None, device="cpu",
             seed: int | None = None, action_mode: str = "raise", init: str | None = None,
             network: str | dict | None = None, load_p=None, gen_p_max=None, stagger: bool = False,
             **surrogate_kwargs) -> EnvBase:
    """Build a batched env of ``num_envs`` grids.

    Args:
        surrogate: ``"none"`` (the true simulator), ``"gym_anm"`` (the original package, ANM6-Easy only, slow), or
            a registered surrogate (``pinn``, ``xgb``, ``rf``, ``dt``, ``lr``, ``dnn``; see
            :func:`anm_torchrl.surrogates.available_surrogates`).
        num_envs: batch size.
        max_steps: episode time limit (``StepCounter``: ``truncated``/``done`` at that step); gym-anm has
            none, the literature evaluates over 3,000 steps.
        device: torch device.
        seed: reset seed.
        action_mode: ``"raise"`` or ``"clip"`` for actions outside the box.
        init: reset distribution (``"gym_anm"``, ``"intended"``, ``"uniform"``); default ``"gym_anm"`` for the
            true ANM6-Easy simulator and ``"uniform"`` for other networks and for surrogates.
        network: a registered network name (:func:`anm_torchrl.networks.list_networks`) or a gym-anm network dict
            (then with ``load_p`` and ``gen_p_max``); None = ANM6-Easy. A surrogate is loaded (or trained) for
            that network's simulator.
        load_p, gen_p_max: (T, n_load), (T, n_gen) MW profiles (see :func:`network_arguments`).
        stagger: with ``max_steps``, cut each env's first episode after a uniform 1..max_steps steps
            (:class:`StaggeredStepCounter`, drawn from ``seed``).
        **surrogate_kwargs: passed to the surrogate's loader (e.g. ``dataset="agent"``, ``path=...``).
    """
    num_envs = check_integer("num_envs", num_envs, low=1)  # 2.7 is an error, not 2 envs
    max_steps = check_integer("max_steps", max_steps, low=1, optional=True)
    seed = check_integer("seed", seed, optional=True)
    if not isinstance(stagger, bool):
        raise ValueError(f"stagger must be True or False, got {stagger!r}")
    if stagger and max_steps is None:
        raise ValueError("stagger=True needs a time limit (max_steps) to stagger")
    if surrogate in (None, *TRUE_SIMULATORS) and surrogate_kwargs:
        raise ValueError(f"surrogate={surrogate!r} takes no surrogate options, got {sorted(surrogate_kwargs)}")
    if surrogate in (None, "none"):
        env = make_true_env(num_envs, device, seed, action_mode, init, network, load_p, gen_p_max)
    elif surrogate == "gym_anm":
        if network_arguments(network, load_p, gen_p_max) is not None:
            raise gym_anm_only("surrogate", network)
        check_gym_anm_options(init, action_mode)
        env = make_gym_anm_env(num_envs, device=device, seed=seed)
    else:
        # the surrogate runs on this network's simulator (its tables and profiles); None = ANM6-Easy's. Built as
        # network_simulator(name) builds it for the recipes, so the model is looked up under the key it was saved under
        kwargs = network_arguments(network, load_p, gen_p_max)
        sim = None if kwargs is None else network_simulator(**kwargs, device=device)
        model = load_surrogate_in_home(surrogate, sim=sim, device=device, **surrogate_kwargs)
        sim = network_simulator(ANM6_EASY, device=device) if sim is None else sim  # SurrogateEnv needs its network
        env = SurrogateEnv(model, num_envs, device=device, seed=seed, action_mode=action_mode,
                           init=init or "uniform", sim=sim)
    if max_steps is not None:
        counter = StaggeredStepCounter(max_steps, seed) if stagger else StepCounter(int(max_steps))
        if isinstance(env, TransformedEnv):  # gym_anm: extend its transforms rather than nest envs
            env.append_transform(counter)
        else:
            env = TransformedEnv(env, counter)
    return env


def surrogate_options(surrogate: Mapping) -> dict:
    """A config's ``surrogate`` group as :func:`make_env` / :func:`load_surrogate` keyword arguments (all but
    ``name``): one home for that mapping (the training env, SHAC's PINN model, the recipes' early check)."""
    return {k: v for k, v in surrogate.items() if k != "name"}


def make_train_env(surrogate: dict, num_envs: int, max_steps: int | None, seed: int, action_mode: str,
                   init: str | None, device: str, threads: int, network: str | None = None, stagger: bool = False):
    """The training env: ``make_env`` + ``RewardSum`` (episode returns for logging). Also a collector-worker factory."""
    from torchrl.envs import RewardSum

    torch.set_num_threads(int(threads))
    options = surrogate_options(surrogate)
    env = make_env(surrogate["name"], num_envs=num_envs, max_steps=max_steps, device=device, seed=seed,
                   action_mode=action_mode, init=init, network=network, stagger=stagger, **options)
    return env.append_transform(RewardSum()) if isinstance(env, TransformedEnv) else TransformedEnv(env, RewardSum())


def train_env_kwargs(cfg, device: str, num_workers: int = 1) -> dict:
    """:func:`make_train_env`'s arguments (all but ``seed``) from the config's ``env``, ``surrogate``, ``network``."""
    from omegaconf import OmegaConf

    return dict(surrogate=OmegaConf.to_container(cfg.surrogate, resolve=True),
                num_envs=int(cfg.env.num_envs) // num_workers, max_steps=cfg.env.max_steps,
                action_mode=cfg.env.action_mode, init=cfg.env.init, device=str(device), threads=int(cfg.threads),
                network=cfg.network, stagger=cfg.env.get("stagger", False))
