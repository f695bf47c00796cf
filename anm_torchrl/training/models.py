"""Policy and value networks for any env of the package: a bounded ``TanhNormal`` actor (PPO's with a
state-independent scale, SAC's with a state-dependent one), a value network (PPO), twin Q networks (SAC), fixed
observation normalisation.

Everything is built from the env's specs only (``observation`` bounds and ``action`` box), so the same factory
serves the true simulator, gym-anm and every surrogate.

Observation normalisation uses *fixed* statistics from the ``observation`` ``Bounded`` spec (no running
statistics: nothing to synchronise between collector workers, nothing that drifts between training on a surrogate
and evaluating on the true simulator): ``loc`` = centre of the box, ``scale`` = its half-width, capped at
``max_scale``. The cap matters for ANM6-Easy: the slack generator's P/Q bounds are a loose ±200 MW/MVAr, while
in practice they stay within about ±100 (−Σ of the other devices' ranges); an uncapped scale of 200 would squash
the slack, which carries the grid's net balance, into ±0.5. With ``max_scale=50`` it spans about ±2. Normalised
values are clipped to ±``clip``.
"""

from __future__ import annotations

import math

import torch
from tensordict.nn import AddStateIndependentNormalScale, NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

from anm_torchrl.training.config_checks import ACTIVATION_NAMES

class _SigmoidTanh(torch.autograd.Function):
    """tanh(x) as 2 sigmoid(2x) - 1 (equal to round-off, ~1e-7), backward (1 - y^2) from the output alone."""

    @staticmethod
    def forward(ctx, x):
        y = torch.sigmoid(2 * x).mul_(2).sub_(1)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad):
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)  # the fused kernel nn.Tanh uses: grad (1 - y^2)


class SigmoidTanh(nn.Module):
    """``model.activation=tanh_sigmoid``: tanh through the sigmoid, opt-in for speed. With torch 2.13's CPU build on a
    2-core AMD EPYC VM ``torch.tanh`` of a (16384, 64) float32 batch takes 3.0 ms, ``torch.sigmoid`` 0.42 ms and a
    64 x 64 matmul 1.5 ms; ``nn.Tanh`` was a fifth of PPO's loop (py-spy). Not the default: its round-off differs
    from ``torch.tanh``'s, so the recorded runs would not repeat to the last digit."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _SigmoidTanh.apply(x)


ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU, "silu": nn.SiLU,
               "tanh_sigmoid": SigmoidTanh}
# the config checks name them without importing torch (a wrong value fails before the heavy imports)
assert set(ACTIVATIONS) == set(ACTIVATION_NAMES), "config_checks.ACTIVATION_NAMES must list ACTIVATIONS' keys"


class ObservationNormalizer(nn.Module):
    """``clamp((x - loc) / scale, -clip, clip)`` with fixed buffers ``loc``, ``scale`` (obs_dim,).

    The buffers travel in the actor's and critic's ``state_dict``, so a saved policy normalises by itself.
    """

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, clip: float = 5.0,
                 time_of_day: tuple[int, int] | None = None, forecast: ProfileForecast | None = None):
        super().__init__()
        loc, scale = torch.as_tensor(loc, dtype=torch.float32), torch.as_tensor(scale, dtype=torch.float32)
        if loc.shape != scale.shape or loc.ndim != 1:
            raise ValueError(f"loc and scale must be 1-D of equal shape, got {tuple(loc.shape)}, {tuple(scale.shape)}")
        if not (torch.isfinite(loc).all() and torch.isfinite(scale).all() and (scale > 0).all()):
            raise ValueError(f"normalisation statistics must be finite with scale > 0; got loc {loc.tolist()}, "
                             f"scale {scale.tolist()}")
        self.register_buffer("loc", loc)
        self.register_buffer("scale", scale)
        self.clip = float(clip)
        if time_of_day is not None and not (0 <= int(time_of_day[0]) < loc.shape[0] and int(time_of_day[1]) >= 2):
            raise ValueError(f"time_of_day must be (index < {loc.shape[0]}, period >= 2), got {time_of_day}")
        self.time_of_day = None if time_of_day is None else (int(time_of_day[0]), int(time_of_day[1]))
        self.forecast = forecast
        self.out_features = (int(loc.shape[0]) + (2 if time_of_day is not None else 0)
                             + (forecast.out_features if forecast is not None else 0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = ((x - self.loc) / self.scale).clamp(-self.clip, self.clip)
        parts = [z]
        if self.time_of_day is not None:
            index, period = self.time_of_day
            # the time index wraps (95 -> 0 on ANM6-Easy): as a number, midnight is the farthest apart two steps are
            phase = (2 * math.pi / period) * torch.remainder(x[..., index], period)
            parts += [torch.sin(phase)[..., None], torch.cos(phase)[..., None]]
        if self.forecast is not None:
            parts.append(self.forecast(x))
        return parts[0] if len(parts) == 1 else torch.cat(parts, -1)

    def stats(self) -> dict[str, torch.Tensor]:
        """``{"loc", "scale"}`` copies (for checkpoints)."""
        return {"loc": self.loc.detach().clone(), "scale": self.scale.detach().clone()}


def observation_stats(spec: Bounded, max_scale: float | None = 50.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre and half-width (capped at ``max_scale``) of an unbatched ``Bounded`` observation spec (obs_dim,).

    Entries with a non-finite bound or zero width get loc 0 (or the finite centre) and scale 1.
    """
    low, high = spec.space.low.to(torch.float64), spec.space.high.to(torch.float64)
    while low.ndim > 1:  # a batched spec: every row has the same bounds
        low, high = low[0], high[0]
    finite = torch.isfinite(low) & torch.isfinite(high)
    loc = torch.where(finite, (low + high) / 2, torch.zeros_like(low))
    scale = torch.where(finite, (high - low) / 2, torch.ones_like(low))
    if max_scale is not None:
        scale = scale.clamp(max=float(max_scale))
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    return loc.float(), scale.float()


def initial_mean_bias(action: torch.Tensor, low: torch.Tensor, high: torch.Tensor, clip: float) -> torch.Tensor:
    """Pre-tanh bias (A,) that makes the actor's deterministic action (its ``TanhNormal`` mean mapped into the box,
    ``low + (high - low)(1 + tanh(b)) / 2``) equal ``action`` (A,), with ``|tanh(b)|`` capped at ``clip`` < 1
    (a target on the box's edge would need an infinite bias; ``clip`` = 0.98 puts it 1 % of the width inside).

    Raises:
        ValueError: shapes differ, ``clip`` is not in (0, 1), or ``action`` lies outside [low, high].
    """
    action, low, high = (torch.as_tensor(x, dtype=torch.float64) for x in (action, low, high))
    if not action.shape == low.shape == high.shape or action.ndim != 1:
        raise ValueError(f"action, low and high must be 1-D of equal shape, got {tuple(action.shape)}, "
                         f"{tuple(low.shape)}, {tuple(high.shape)}")
    if not 0.0 < float(clip) < 1.0:
        raise ValueError(f"clip must be in (0, 1), got {clip}")
    if ((action < low) | (action > high)).any():
        raise ValueError(f"initial action {action.tolist()} lies outside the action box [{low.tolist()}, "
                         f"{high.tolist()}]")
    u = (2 * (action - low) / (high - low) - 1).clamp(-float(clip), float(clip))
    return torch.atanh(u).float()


def _initial_action(env: EnvBase, init_action: torch.Tensor | str | None) -> torch.Tensor | None:
    """``make_actor``'s ``init_action`` as an action tensor (A,) MW/MVAr, or None for the box centre."""
    if init_action is None or isinstance(init_action, torch.Tensor):
        return init_action
    if init_action == "center":
        return None
    if init_action != "do_nothing":
        raise ValueError(f"init_action must be 'center', 'do_nothing', an action tensor or None; got {init_action!r}")
    from anm_torchrl.baselines.simple import DoNothingPolicy

    sim = getattr(_base_env(env), "sim", None)
    if sim is None:
        raise ValueError(f"init_action='do_nothing' needs an env with a simulator (.sim), got {type(env).__name__}")
    return DoNothingPolicy(sim).action_value


def _base_env(env: EnvBase) -> EnvBase:
    """The package env under TorchRL's transforms (``TransformedEnv.base_env``), or ``env`` itself."""
    from torchrl.envs import TransformedEnv

    return env.base_env if isinstance(env, TransformedEnv) else env


def _unbatched(spec, key: str):
    spec = spec[key] if key in spec.keys() else spec
    return spec[(0,) * (spec.ndim - 1)] if spec.ndim > 1 else spec


def _mlp(in_features: int, out_features: int, cells, activation: str) -> nn.Module:
    return MLP(in_features=in_features, out_features=out_features, num_cells=list(cells),
               activation_class=ACTIVATIONS[activation])


def _orthogonal_init(mlp: nn.Module, last_gain: float) -> nn.Module:
    """Orthogonal weights (gain sqrt(2), ``last_gain`` on the last layer) and zero biases, in place."""
    layers = [m for m in mlp.modules() if isinstance(m, nn.Linear)]
    for i, layer in enumerate(layers):
        nn.init.orthogonal_(layer.weight, last_gain if i == len(layers) - 1 else 2 ** 0.5)
        nn.init.zeros_(layer.bias)
    return mlp


def time_of_day_feature(env: EnvBase, key: str = "model.time_features") -> tuple[int, int]:
    """``(index, period)`` of the time-of-day input of ``env``'s observation: the position of its ``aux`` entry
    (gym-anm's time index: ANM6-Easy's 0..95, a feeder's row of its load/generation tables) and the steps per day
    ``24 / delta_t`` (96 at 15-min steps); the time of day is ``aux mod period``. ``key``: the config key that
    asked for it, named in the errors.

    Raises:
        ValueError: the observation has no ``aux`` entry, or the env has no observation map.
    """
    base = _base_env(env)
    obs_map = getattr(base, "obs_map", None)
    if obs_map is None:
        raise ValueError(f"{key} needs an env with an observation map (.obs_map), got "
                         f"{type(base).__name__}")
    offset = 0
    for name, rows, _ in obs_map.entries:
        if name == "aux":
            return offset, int(round(24 / float(base.sim.net.delta_t)))
        offset += int(rows.numel())
    raise ValueError(f"{key} needs the time index ('aux') in the observation")


class ProfileForecast(nn.Module):
    """The next ``steps`` steps of every load's P and every generator's potential, read from the network's profiles
    at the observation's time index: a **perfect forecast** (what MPC-perfect and the optimum see), which a
    controller in the field does not have. Opt-in (``model.forecast_steps``); never in a default.

    ``table`` (T, n_load + n_gen) holds the profiles as the simulator applies them (clipped to the devices' limits,
    p.u.), each column divided by its largest magnitude over T (``scale``, p.u.), so entries lie in [-1, 1]. It is
    rebuilt from the env's simulator whenever the model is (a non-persistent buffer: checkpoints stay small, and a
    saved policy is loaded with its network's env).
    """

    def __init__(self, table: torch.Tensor, aux_index: int, steps: int):
        """``table`` (T, m) p.u. as the simulator applies it; ``aux_index`` the observation's time index entry."""
        super().__init__()
        if table.ndim != 2 or table.shape[0] < 1 or not torch.isfinite(table).all():
            raise ValueError(f"the forecast table must be a finite (T, m) tensor, got shape {tuple(table.shape)}")
        if int(steps) < 1:
            raise ValueError(f"forecast steps must be >= 1, got {steps}")
        peak = table.abs().amax(0)
        self.register_buffer("scale", torch.where(peak > 0, peak, torch.ones_like(peak)).float(), persistent=False)
        self.register_buffer("table", (table / self.scale.to(table)).float(), persistent=False)
        self.register_buffer("offsets", torch.arange(1, int(steps) + 1), persistent=False)
        self.aux_index = int(aux_index)
        self.out_features = int(steps) * int(table.shape[1])

    @classmethod
    def from_env(cls, env: EnvBase, steps: int) -> ProfileForecast:
        """The forecast of ``env``'s simulator (``env.sim``: its load and potential series, the observation's time
        index ``aux``, as :func:`time_of_day_feature` finds it)."""
        aux_index, _ = time_of_day_feature(env, "model.forecast_steps")
        sim = _base_env(env).sim
        t = torch.arange(sim.n_time, device=sim.net.dev.device)
        return cls(torch.cat([sim.loads_at(t)[0], sim.p_pot_at(t)], -1).double().cpu(), aux_index, steps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., obs_dim) observation -> (..., steps x m): rows t+1..t+steps (mod T) of the table, t = its time
        index (gym-anm's next state reads row t+1)."""
        n = self.table.shape[0]
        t = torch.remainder(x[..., self.aux_index].round().long(), n)
        rows = self.table[torch.remainder(t[..., None] + self.offsets, n)]
        return rows.flatten(-2)


def _specs(env: EnvBase, obs_key: str, activation: str, max_obs_scale, obs_clip, obs_stats, time_features=False,
           forecast_steps: int = 0):
    """(obs spec, action spec, normaliser) of ``env``, after checking ``activation``."""
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    obs_spec = _unbatched(env.observation_spec, obs_key)
    act_spec = _unbatched(env.full_action_spec, "action")
    if obs_stats is None:
        if not isinstance(obs_spec, Bounded):
            raise ValueError(f"observation spec {obs_key!r} must be Bounded to derive normalisation statistics, got "
                             f"{type(obs_spec).__name__}; pass obs_stats")
        loc, scale = observation_stats(obs_spec, max_obs_scale)
    else:
        loc, scale = obs_stats["loc"], obs_stats["scale"]
    forecast = ProfileForecast.from_env(env, forecast_steps) if forecast_steps else None
    return obs_spec, act_spec, ObservationNormalizer(loc, scale, obs_clip,
                                                     time_of_day_feature(env) if time_features else None, forecast)


def make_actor(env: EnvBase, cells=(64, 64), activation: str = "tanh", max_obs_scale: float | None = 50.0,
               obs_clip: float = 5.0, init_log_std: float = -2.0, obs_stats: dict[str, torch.Tensor] | None = None,
               obs_key: str = "observation", init_action: torch.Tensor | str | None = None,
               init_action_clip: float = 0.98, state_dependent_scale: bool = False,
               critic_cells=None, time_features: bool = False, forecast_steps: int = 0,
               ) -> tuple[ProbabilisticActor, ObservationNormalizer, nn.Module | None]:
    """The bounded ``TanhNormal`` actor of every algorithm, and its observation normaliser.

    Args:
        env: any env of the package (only its ``observation`` / ``action`` specs are read, and ``env.sim`` for
            ``init_action="do_nothing"``).
        cells: hidden layer widths.
        activation: one of :data:`ACTIVATIONS`.
        max_obs_scale: cap on the normalisation half-width (see the module docstring); None for no cap.
        obs_clip: clip of the normalised observation.
        init_log_std: initial log standard deviation of the pre-tanh Gaussian (state-independent scale: its
            initial value; state-dependent: the bias of the scale head's softplus, so the untrained policy has it).
        obs_stats: ``{"loc", "scale"}`` to use instead of the spec's (e.g. from a checkpoint).
        obs_key: observation key read by the network.
        init_action: the untrained policy's deterministic action: None or ``"center"`` (bias 0, the centre of the
            box), ``"do_nothing"`` (the do-nothing action of ``env``'s simulator ``env.sim``: renewables at their
            maximum, no reactive power, storage idle) or an (A,) action in MW/MVAr; the last layer's bias is set by
            :func:`initial_mean_bias` (the weights are drawn identically either way).
        init_action_clip: ``clip`` of :func:`initial_mean_bias`.
        state_dependent_scale: False (PPO): one learned log-std per action; True (SAC): the MLP outputs the scale
            too (``NormalParamExtractor``).
        critic_cells: with a value: also an initialised (obs_dim -> 1) MLP of these widths, built right after the
            actor's MLP and before either is initialised (the order of random draws every PPO run has used).
        time_features: also feed sin/cos of the time of day (:func:`time_of_day_feature`) to every network: two
            inputs more, continuous across midnight. Reads the observation only (no forecast).
        forecast_steps: also feed the next ``forecast_steps`` steps of the network's loads and potentials
            (:class:`ProfileForecast`, a perfect forecast; needs ``env.sim``); 0: none.

    Returns:
        ``ProbabilisticActor`` writing ``"action"`` (…, A) within the action box (a ``TanhNormal`` scaled to
        [low, high]; deterministic mode = its mean) and ``"action_log_prob"``; the normaliser module; the value
        MLP or None.
    """
    init_action = _initial_action(env, init_action)
    obs_spec, act_spec, normalizer = _specs(env, obs_key, activation, max_obs_scale, obs_clip, obs_stats,
                                            time_features, int(forecast_steps))
    low, high = act_spec.space.low.float(), act_spec.space.high.float()
    # entries whose range is a single value (QMIN = QMAX, PMIN = PMAX) are written at it, not sampled
    free = (high > low).nonzero().flatten()
    if free.numel() == 0:
        raise ValueError("every action entry's range is a single value: a policy would have nothing to choose")
    partly_fixed = free.numel() < low.numel()
    obs_dim, act_dim = normalizer.out_features, int(free.numel())
    mlp = _mlp(obs_dim, act_dim * (2 if state_dependent_scale else 1), cells, activation)
    value_mlp = None if critic_cells is None else _mlp(obs_dim, 1, critic_cells, activation)
    _orthogonal_init(mlp, 0.01)  # a small last actor layer: the untrained mean is (almost) its bias
    if value_mlp is not None:
        _orthogonal_init(value_mlp, 1.0)
    last = [m for m in mlp.modules() if isinstance(m, nn.Linear)][-1]
    with torch.no_grad():
        if init_action is not None:
            last.bias[:act_dim].copy_(initial_mean_bias(torch.as_tensor(init_action)[free], low[free], high[free],
                                                        init_action_clip))
        if state_dependent_scale:  # softplus(bias) = exp(init_log_std) at the untrained policy
            last.bias[act_dim:].fill_(float(torch.log(torch.expm1(torch.tensor(float(init_log_std)).exp()))))
    head = (NormalParamExtractor(scale_mapping="softplus", scale_lb=1e-4) if state_dependent_scale
            else AddStateIndependentNormalScale(act_dim, scale_lb=1e-4, init_value=float(init_log_std)))
    if partly_fixed:
        from anm_torchrl.training.distributions import PartlyFixedTanhNormal

        dist_class, dist_kwargs = PartlyFixedTanhNormal, {"low": low[free], "high": high[free], "free": free,
                                                          "fixed": low, "tanh_loc": False}
    else:  # every entry chosen: TorchRL's TanhNormal itself
        dist_class, dist_kwargs = TanhNormal, {"low": low, "high": high, "tanh_loc": False}
    actor = ProbabilisticActor(
        TensorDictModule(nn.Sequential(normalizer, mlp, head), in_keys=[obs_key], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=act_spec,
        distribution_class=dist_class,
        distribution_kwargs=dist_kwargs,
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )
    return actor, normalizer, value_mlp


def make_ppo_models(env: EnvBase, actor_cells=(64, 64), critic_cells=(64, 64), activation: str = "tanh",
                    max_obs_scale: float | None = 50.0, obs_clip: float = 5.0, init_log_std: float = -2.0,
                    obs_stats: dict[str, torch.Tensor] | None = None, obs_key: str = "observation",
                    init_action: torch.Tensor | str | None = None, init_action_clip: float = 0.98,
                    time_features: bool = False, state_dependent_scale: bool = False, forecast_steps: int = 0,
                    ) -> tuple[ProbabilisticActor, ValueOperator, ObservationNormalizer]:
    """PPO's actor (:func:`make_actor`, state-independent scale unless ``state_dependent_scale``), its value network
    (``"state_value"``, separate weights as SB3's MlpPolicy, the same normaliser) and the normaliser. Arguments as
    :func:`make_actor`."""
    actor, normalizer, value_mlp = make_actor(env, actor_cells, activation, max_obs_scale, obs_clip, init_log_std,
                                              obs_stats, obs_key, init_action, init_action_clip,
                                              critic_cells=critic_cells, time_features=time_features,
                                              state_dependent_scale=state_dependent_scale,
                                              forecast_steps=forecast_steps)
    critic = ValueOperator(nn.Sequential(normalizer, value_mlp), in_keys=[obs_key])
    return actor, critic, normalizer


class _QInput(nn.Module):
    """``cat(normalise(observation), action scaled to [-1, 1])`` for a Q network."""

    def __init__(self, normalizer: ObservationNormalizer, low: torch.Tensor, high: torch.Tensor, mlp: nn.Module):
        super().__init__()
        self.normalizer, self.mlp = normalizer, mlp
        self.register_buffer("a_loc", ((high + low) / 2).float())
        self.register_buffer("a_scale", ((high - low) / 2).clamp(min=1e-6).float())

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([self.normalizer(obs), (action - self.a_loc) / self.a_scale], -1))


def make_sac_models(env: EnvBase, actor_cells=(256, 256), critic_cells=(256, 256), activation: str = "relu",
                    max_obs_scale: float | None = 50.0, obs_clip: float = 5.0, init_log_std: float = -1.0,
                    obs_stats: dict[str, torch.Tensor] | None = None, obs_key: str = "observation",
                    init_action: torch.Tensor | str | None = None, init_action_clip: float = 0.98,
                    time_features: bool = False, forecast_steps: int = 0,
                    ) -> tuple[ProbabilisticActor, ValueOperator, ObservationNormalizer]:
    """SAC's actor (:func:`make_actor`, state-dependent scale), one Q network template (``"state_action_value"``
    from the normalised observation and the action scaled to [-1, 1]; ``SACLoss`` makes its twins) and the
    normaliser. Arguments as :func:`make_actor`."""
    actor, normalizer, _ = make_actor(env, actor_cells, activation, max_obs_scale, obs_clip, init_log_std, obs_stats,
                                      obs_key, init_action, init_action_clip, state_dependent_scale=True,
                                      time_features=time_features, forecast_steps=forecast_steps)
    act_spec = _unbatched(env.full_action_spec, "action")
    low, high = act_spec.space.low.float(), act_spec.space.high.float()
    obs_dim, act_dim = normalizer.out_features, int(low.shape[-1])
    q = _QInput(normalizer, low, high, _orthogonal_init(_mlp(obs_dim + act_dim, 1, critic_cells, activation), 1.0))
    qvalue = ValueOperator(q, in_keys=[obs_key, "action"], out_keys=["state_action_value"])
    return actor, qvalue, normalizer
