"""Deterministic evaluation of a policy on the true simulator (``ANM6Env``) or on gym-anm itself.

Protocol (Henry & Ernst's gym-anm paper, used by the PPO recipe and ``recipes/evaluate.py``):

* a fixed set of initial states, drawn once from gym-anm's reset distribution with a seed
  (:func:`draw_initial_states`);
* one episode of at most ``max_steps`` steps (default 3,000) per initial state, the policy in deterministic mode;
* an episode ends at its first termination (power flow did not converge): rewards are counted up to and including
  that step, nothing after it;
* metrics per episode, then averaged over episodes:

  ============================  ======================================================================
  ``return``                    Σ_t r_t (undiscounted)
  ``discounted_return``         Σ_t γ^t r_t, γ = 0.995 (the gym-anm paper's score)
  ``e_loss``                    Σ_t ΔE_c,t — clipped energy-loss term of the reward (p.u.·h, clipped at 1 per step)
  ``penalty``                   Σ_t Pen_c,t — clipped constraint penalty λΦ (clipped at 100 per step)
  ``steps``                     number of counted steps (≤ max_steps)
  ``terminated``                fraction of episodes that terminated
  ============================  ======================================================================

  On a terminal step the energy-loss and penalty terms are set to the clipping values (1, 100), as gym-anm does,
  so ``return == -(e_loss + penalty)`` for episodes that do not terminate.

:func:`evaluate_policy` rolls every episode out in one batched ``ANM6Env`` (``env.rollout``'s steps with
``break_when_any_done=False``, the states set with ``reset(..., set_state=True)``; the package's own envs are stepped
through their ``_step``, the same values without TorchRL's per-step bookkeeping); :func:`evaluate_policy_gym_anm`
steps gym-anm's ``ANM6Easy`` environments in lock-step (one batched policy call per step), injecting the same
initial states through gym-anm's ``init_state`` hook (gym-anm's ``reset(options=...)`` cannot set a state).
Injected states are reproduced by gym-anm to ~1e-12 MW, so both simulators run the same episodes.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from anm_torchrl._extras import require
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.grid import reset as grid_reset
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks import ANM6_EASY
from anm_torchrl.networks import simulator as network_simulator

EVAL_GAMMA = 0.995
EVAL_MAX_STEPS = 3000
METRICS = ("return", "discounted_return", "e_loss", "penalty", "steps", "terminated")


@dataclasses.dataclass
class EvalResult:
    """Per-episode results (tensors of shape (E,)) and their means (:meth:`metrics`)."""

    returns: torch.Tensor
    discounted_returns: torch.Tensor
    e_loss: torch.Tensor
    penalty: torch.Tensor
    steps: torch.Tensor
    terminated: torch.Tensor
    max_steps: int
    gamma: float
    wall_time: float

    @property
    def num_episodes(self) -> int:
        return int(self.returns.numel())

    def metrics(self) -> dict[str, float]:
        """Means over episodes, keyed as :data:`METRICS` (``terminated`` is the terminated fraction)."""
        return {
            "return": float(self.returns.mean()),
            "discounted_return": float(self.discounted_returns.mean()),
            "e_loss": float(self.e_loss.mean()),
            "penalty": float(self.penalty.mean()),
            "steps": float(self.steps.float().mean()),
            "terminated": float(self.terminated.float().mean()),
        }


def reset_to(env: EnvBase, states: torch.Tensor) -> TensorDict:
    """``env`` (batch E) reset into ``states`` (E, state_dim) MW/MVAr/MWh (``reset(..., set_state=True)``, which the
    package's true and surrogate envs honour); returns the reset TensorDict."""
    states = torch.as_tensor(states)
    td = TensorDict({"state": states.to(env.device, torch.float64)}, [len(states)], device=env.device)
    return env.reset(td, set_state=True)


def draw_initial_states(num_episodes: int, seed: int, sim: GridSimulator | None = None,
                        init: str = "gym_anm") -> torch.Tensor:
    """``num_episodes`` initial states (E, state_dim) float64 MW/MVAr/MWh from a reset distribution.

    Args:
        num_episodes: E.
        seed: seed of a fresh ``torch.Generator`` (the same seed gives the same states).
        sim: the network's simulator (default ANM6-Easy).
        init: the env's reset distribution (``env.init``): ``"gym_anm"`` / ``"intended"`` (ANM6-Easy's
            ``init_state``, with / without its unit quirks) or ``"uniform"`` (``grid.reset.random_state``, the
            default of ``ANMEnv`` on other networks).
    """
    sim = network_simulator(ANM6_EASY) if sim is None else sim
    num_episodes = check_integer("num_episodes", num_episodes, low=1)  # 2.5 gave 2 states, seed 0.9 seed 0's
    generator = torch.Generator(device=sim.net.dev.device).manual_seed(check_integer("seed", seed, low=0))
    if init == "uniform":
        states, _ = grid_reset.random_state(sim, num_episodes, generator)
    elif init in ("gym_anm", "intended"):
        states, _ = grid_reset.gym_anm_reset(sim, num_episodes, generator, intended=init == "intended")
    else:
        raise ValueError(f"init must be gym_anm, intended or uniform, got {init!r}")
    return states.cpu()


def episode_metrics(reward: torch.Tensor, e_loss: torch.Tensor, penalty: torch.Tensor, terminated: torch.Tensor,
                    gamma: float = EVAL_GAMMA, costs_clipping: tuple[float, float] = (1.0, 100.0),
                    max_steps: int | None = None, wall_time: float = 0.0) -> EvalResult:
    """Episode metrics from step arrays of shape (E, T) (float rewards and raw reward terms, bool terminations).

    Steps after an episode's first termination are ignored; the terminal step itself counts. ``e_loss`` and
    ``penalty`` are clipped as in the reward (``costs_clipping``) and set to the clipping values on terminal steps.
    """
    reward, e_loss, penalty = (x.to(torch.float64) for x in (reward, e_loss, penalty))
    terminated = terminated.to(torch.bool)
    n_steps = reward.shape[1]
    # alive[t]: no termination strictly before t
    before = torch.cumsum(terminated.long(), 1) - terminated.long()
    alive = before == 0
    e_c = torch.sign(e_loss) * e_loss.abs().clamp(max=costs_clipping[0])
    pen_c = penalty.clamp(min=0.0, max=costs_clipping[1])
    e_c = torch.where(terminated, torch.full_like(e_c, costs_clipping[0]), e_c)
    pen_c = torch.where(terminated, torch.full_like(pen_c, costs_clipping[1]), pen_c)
    # NaN terms outside the counted steps must not leak into the sums
    zero = torch.zeros((), dtype=torch.float64)
    discount = gamma ** torch.arange(n_steps, dtype=torch.float64)
    return EvalResult(
        returns=torch.where(alive, reward, zero).sum(1),
        discounted_returns=torch.where(alive, reward * discount, zero).sum(1),
        e_loss=torch.where(alive, e_c, zero).sum(1),
        penalty=torch.where(alive, pen_c, zero).sum(1),
        steps=alive.sum(1),
        terminated=(terminated & alive).any(1),
        max_steps=int(max_steps if max_steps is not None else n_steps),
        gamma=float(gamma),
        wall_time=float(wall_time),
    )


@torch.no_grad()
def evaluate_policy(policy: TensorDictModuleBase, initial_states: torch.Tensor, max_steps: int = EVAL_MAX_STEPS,
                    gamma: float = EVAL_GAMMA, env: EnvBase | None = None,
                    exploration_type: ExplorationType = ExplorationType.DETERMINISTIC,
                    reference: bool = False) -> EvalResult:
    """Roll ``policy`` out from every initial state (E, 18) in one batched env of E grids.

    Args:
        policy: reads ``"observation"`` and/or ``"state"``, writes ``"action"`` (E, 6) MW/MVAr.
        initial_states: (E, 18) float64 states (e.g. :func:`draw_initial_states`).
        max_steps: episode length T.
        gamma: discount of ``discounted_return``.
        env: an env with batch size [E] honouring ``reset(..., set_state=True)``; default a new ``ANM6Env(E)``
            (the true simulator).
        exploration_type: default deterministic (the distribution's mean, inside the action box).
        reference: step through TorchRL's ``env.step_and_maybe_reset`` and the policy's own call, as
            ``env.rollout`` does: the path the default one equals bit for bit (``benchmarks.evaluation`` times
            both; ~2x slower on the package's envs) for a policy that reads what TorchRL's modules declare they
            read (a module reading keys it does not declare, e.g. its own log-probability of the previous step,
            which the default path does not write for the recipes' actors, needs ``reference=True``).
    """
    from anm_torchrl.envs import ANM6Env

    n = int(initial_states.shape[0])
    max_steps = check_integer("max_steps", max_steps, low=1)  # 0 raised an IndexError, 2.5 ran 2 steps
    if env is None:
        env = ANM6Env(n, seed=0)
    if tuple(env.batch_size) != (n,):
        raise ValueError(f"env batch size {tuple(env.batch_size)} does not match {n} initial states")
    sim = getattr(env, "sim", None)
    clipping = tuple(sim.costs_clipping) if sim is not None else (1.0, 100.0)
    t0 = time.perf_counter()
    td = reset_to(env, initial_states)
    act = _acting(policy, exploration_type, reference)
    keys = ("reward", ("grid", "e_loss"), ("grid", "penalty"), "terminated")
    steps: dict = {k: [] for k in keys}
    with set_exploration_type(exploration_type):
        if not reference and _steps_itself(env):
            _own_steps(env, act, td, int(max_steps), keys, steps)
        else:
            # ``env.rollout``'s loop, keeping only what the metrics read (stacking every step's TensorDict cost
            # more than the simulator). Auto-resets after a termination are harmless: everything after it is masked
            for t in range(int(max_steps)):
                td = act(td)
                if t == max_steps - 1:
                    out = env.step(td)
                else:
                    out, td = env.step_and_maybe_reset(td)
                nxt = out.get("next")
                for k in keys:
                    steps[k].append(nxt.get(k, None))
    nan = torch.full((n, int(max_steps)), float("nan"))

    def series(key) -> torch.Tensor:
        return nan if steps[key][0] is None else torch.stack(steps[key], 1).reshape(n, -1).cpu()

    return episode_metrics(series("reward"), series(("grid", "e_loss")), series(("grid", "penalty")),
                           series("terminated"), gamma=gamma, costs_clipping=clipping, max_steps=max_steps,
                           wall_time=time.perf_counter() - t0)


def _acting(policy: TensorDictModuleBase, exploration_type: ExplorationType, reference: bool = False):
    """``td -> td`` with the policy's action written. A deterministic ``ProbabilisticTensorDictSequential`` of one
    sampled key (the recipes' actors) writes its distribution's deterministic sample alone — the action
    ``policy(td)`` writes in that mode, without the log-probability and the distribution's other outputs (~40 % of
    an evaluation step). ``reference``: the policy's own call always."""
    def call(td):
        td.update(policy(td))  # as ``env.rollout``: a policy may return a new TensorDict
        return td

    module = policy.module[-1] if isinstance(policy, ProbabilisticTensorDictSequential) else None
    keys = getattr(module, "dist_sample_keys", ()) if module is not None else ()
    if reference or exploration_type != ExplorationType.DETERMINISTIC or len(keys) != 1:
        return call
    key = keys[0]
    # a safe actor projects its sample onto its spec, as policy(td) does
    spec = getattr(module, "spec", None) if getattr(module, "safe", False) else None
    spec = spec[key] if spec is not None and key in spec.keys(True) else None

    params_of = dict(zip(module.dist_keys, module.dist_params_keys))
    # the cached transform holds the distribution's box: only where the box is the module's own (its kwargs), not a
    # parameter read from the TensorDict at each step (a state-dependent low / high)
    loc_key = params_of.get("loc") if set(params_of) <= {"loc", "scale"} else None
    squash = []  # TorchRL's TanhNormal: its deterministic sample is its transform of ``loc``, checked at step 1

    def act(td):
        if squash:  # the distribution's object (~30 % of an evaluation step) is not built again
            sample = squash[0](policy.get_dist_params(td).get(loc_key))
        else:
            params = policy.get_dist_params(td)
            dist = policy.build_dist_from_params(params)
            sample = getattr(dist, "deterministic_sample", None)
            if sample is None:  # a torch.distributions class (Normal, Beta, ...) has none: the module's own call
                return call(td)
            transform = getattr(dist, "_t", None)
            if (transform is not None and loc_key is not None and not getattr(dist, "tanh_loc", True)
                    and torch.equal(transform(params.get(loc_key)), sample)):
                squash.append(transform)
        td.set(key, sample if spec is None else spec.project(sample))
        return td

    return act


def _steps_itself(env: EnvBase) -> bool:
    """Whether :func:`evaluate_policy` may step ``env`` through its own ``_step``: the package's envs
    (``ANMEnv``, its presets and ``SurrogateEnv``), not wrapped in transforms."""
    from anm_torchrl.envs import ANMEnv

    return isinstance(env, ANMEnv)


def _own_steps(env, act, td: TensorDict, max_steps: int, keys, steps: dict) -> None:
    """``max_steps`` steps of ``env`` through its ``_step`` (what ``env.step`` runs, without TorchRL's per-step
    bookkeeping), appending each step's ``keys`` to ``steps``. Between steps the TensorDict is carried as
    ``step_and_maybe_reset`` carries it (its ``step_mdp``), and terminated rows are reset through
    ``env.maybe_reset``."""
    for t in range(max_steps):
        td = act(td)
        out = env._step(td)
        for k in keys:
            steps[k].append(out.get(k, None))
        if t < max_steps - 1:
            # the carry step_and_maybe_reset uses (TorchRL's step_mdp, torchrl pinned): the step's outputs over
            # what the policy wrote (its action, an exploration module's state), the reward dropped
            td = env._step_mdp(td.set("next", out))
            if bool(out.get("done").any()):
                td = env.maybe_reset(td)


@torch.no_grad()
def evaluate_policy_gym_anm(policy: TensorDictModuleBase, initial_states: torch.Tensor,
                            max_steps: int = EVAL_MAX_STEPS, gamma: float = EVAL_GAMMA,
                            exploration_type: ExplorationType = ExplorationType.DETERMINISTIC,
                            progress: bool = False) -> EvalResult:
    """Same protocol on the original gym-anm 2.0.1 ``ANM6Easy`` (slow, ≈25 steps/s per episode).

    One gym-anm env per initial state, stepped in lock-step; the policy gets a TensorDict with ``"state"``
    (gym-anm's ``env.state``, float64) and ``"observation"`` (float32) for the episodes still running. The state
    is injected by replacing the env's ``init_state`` before ``reset``; terms are gym-anm's clipped
    ``env.e_loss`` / ``env.penalty``.
    """
    ANM6Easy = require("gym_anm.envs", what="evaluation on gym-anm").ANM6Easy

    n = int(initial_states.shape[0])
    envs, obs = [], []
    for i in range(n):
        env = ANM6Easy()
        s0 = initial_states[i].to(torch.float64).numpy().copy()
        env.init_state = lambda s0=s0: s0.copy()  # gym-anm's reset calls self.init_state()
        o, _ = env.reset(seed=i)
        envs.append(env)
        obs.append(o)
    shape = (n, int(max_steps))
    reward, e_loss, penalty = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    terminated = np.zeros(shape, dtype=bool)
    running = np.ones(n, dtype=bool)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=int(max_steps), desc="gym-anm", leave=False)
    t0 = time.perf_counter()
    with set_exploration_type(exploration_type):
        for t in range(int(max_steps)):
            idx = np.flatnonzero(running)
            if idx.size == 0:
                break
            td = TensorDict({"state": torch.as_tensor(np.stack([envs[i].state for i in idx])),
                             "observation": torch.as_tensor(np.stack([obs[i] for i in idx]), dtype=torch.float32)},
                            [idx.size])
            actions = policy(td).get("action").detach().to(torch.float64).cpu().numpy()
            for k, i in enumerate(idx):
                o, r, term, _, _ = envs[i].step(actions[k])
                obs[i] = o
                reward[i, t], e_loss[i, t], penalty[i, t] = r, envs[i].e_loss, envs[i].penalty
                terminated[i, t] = term
                running[i] = not term
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    clipping = tuple(float(c) for c in envs[0].costs_clipping)
    return episode_metrics(torch.from_numpy(reward), torch.from_numpy(e_loss), torch.from_numpy(penalty),
                           torch.from_numpy(terminated), gamma=gamma, costs_clipping=clipping,
                           max_steps=max_steps, wall_time=time.perf_counter() - t0)

