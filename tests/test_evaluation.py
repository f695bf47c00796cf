"""The evaluation protocol's constants are defined once (``anm_torchrl.evaluation``); configs that spell them agree.

YAML cannot import a Python constant, so the recipes' configs repeat γ = 0.995 and T = 3,000: this test fails when
one of them drifts from :data:`~anm_torchrl.evaluation.EVAL_GAMMA` / :data:`~anm_torchrl.evaluation.EVAL_MAX_STEPS`.
Short smoke presets (``quick``, ``tiny``) shorten T on purpose; only their discount is checked.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from anm_torchrl.evaluation import EVAL_GAMMA, EVAL_MAX_STEPS

CONF = Path(__file__).resolve().parents[1] / "recipes" / "conf"


@pytest.mark.parametrize("file, gamma_key, steps_key", [
    ("eval/default.yaml", "gamma", "max_steps"),
    ("../conf_evaluate/evaluate.yaml", None, None),  # gamma and steps: the run's or the network's test protocol
    ("preset/full.yaml", "test_returns.gamma", "test_returns.max_steps"),
    ("preset/quick.yaml", "test_returns.gamma", None),
    ("preset/tiny.yaml", "test_returns.gamma", None),
])
def test_configs_spell_the_protocol_constants(file, gamma_key, steps_key):
    cfg = OmegaConf.load(CONF / file)
    if gamma_key is None:  # evaluate.py: null, the test protocol's (recipes/evaluate.py test_protocol)
        assert cfg.gamma is None and cfg.steps is None
        return
    assert OmegaConf.select(cfg, gamma_key, throw_on_missing=True) == EVAL_GAMMA, f"{file}: {gamma_key}"
    if steps_key is not None:
        assert OmegaConf.select(cfg, steps_key, throw_on_missing=True) == EVAL_MAX_STEPS, f"{file}: {steps_key}"



def _rollout_reference(policy, states, steps, env):
    """The metrics from ``env.rollout`` (the loop :func:`evaluate_policy` reproduces without its bookkeeping)."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from anm_torchrl.evaluation import episode_metrics, reset_to

    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        roll = env.rollout(steps, policy, tensordict=reset_to(env, states), auto_reset=False,
                           break_when_any_done=False)
    nxt = roll.get("next")
    return episode_metrics(nxt["reward"].squeeze(-1), nxt[("grid", "e_loss")].squeeze(-1),
                           nxt[("grid", "penalty")].squeeze(-1), nxt["terminated"].squeeze(-1))


@pytest.mark.parametrize("kind", ["actor", "plain", "normal", "safe_normal"])
def test_evaluation_equals_the_env_rollout(kind):
    """The recipes' actor (its deterministic sample written directly) and a plain policy give, bit for bit, the
    metrics of ``env.rollout``; the plain policy drives the first grid to voltage collapse (every device absorbing
    reactive power, the storage charging at its limit), so an episode terminates and its later steps are masked."""
    import torch
    from tensordict.nn import TensorDictModule

    from anm_torchrl.envs import ANM6Env
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.models import make_ppo_models

    env = ANM6Env(4, seed=0)
    states = draw_initial_states(4, seed=3)
    if kind == "actor":
        torch.manual_seed(0)
        policy = make_ppo_models(env)[0]
    elif kind in ("normal", "safe_normal"):
        # bug: the fast path read ``deterministic_sample``, which torch.distributions.Normal lacks (AttributeError),
        # and skipped a safe actor's projection onto its spec (an action of 1e3 MW refused by the env)
        from torch.distributions import Normal
        from torchrl.modules import ProbabilisticActor

        loc = 1e3 if kind == "safe_normal" else 1.0

        def net(obs):
            return torch.full((*obs.shape[:-1], 6), loc), torch.ones(*obs.shape[:-1], 6)

        policy = ProbabilisticActor(TensorDictModule(net, ["observation"], ["loc", "scale"]), in_keys=["loc", "scale"],
                                    distribution_class=Normal, spec=env.action_spec, safe=kind == "safe_normal")
    else:
        low, high = env.action_spec.space.low[0], env.action_spec.space.high[0]
        collapse = torch.stack([high[0], high[1], low[2], low[3], high[4], low[5]])
        first = (torch.arange(4) == 0).unsqueeze(1)
        spread = lambda obs: low + (high - low) * torch.sigmoid(obs[:, :6])  # noqa: E731
        policy = TensorDictModule(lambda obs: torch.where(first, collapse, spread(obs)), in_keys=["observation"],
                                  out_keys=["action"])
    got = evaluate_policy(policy, states, max_steps=40, env=env)
    want = _rollout_reference(policy, states, 40, ANM6Env(4, seed=0))
    assert bool(got.terminated[0]) == (kind == "plain") and not bool(got.terminated[1:].any())
    for field in ("returns", "discounted_returns", "e_loss", "penalty", "steps", "terminated"):
        assert torch.equal(getattr(got, field), getattr(want, field)), field


@pytest.mark.parametrize("network", ["case33bw", "random", "surrogate"])
def test_evaluation_steps_the_packages_envs_as_their_rollout(network):
    """:func:`evaluate_policy` steps the package's envs through their ``_step`` and writes the recipes' actor's
    deterministic action from its distribution's transform (built once): bit for bit ``env.rollout``'s metrics on a
    feeder and on a surrogate env whose model ends some episodes (row 0 at its 7th step, row 2 at its 30th; their
    later steps masked), over enough steps for the actor's cached transform to act."""
    import torch
    from tensordict.nn import TensorDictModuleBase

    from anm_torchrl.envs import SurrogateEnv
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.networks import simulator
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.models import make_ppo_models

    if network == "case33bw":
        def make():
            return make_true_env(3, network="case33bw", seed=0)
    elif network == "random":  # a network nobody tuned for: 8 buses, meshed
        from anm_torchrl.networks.random import generate

        case = generate(11, n_bus=8, meshed=True)

        def make():
            return make_true_env(3, network=case.network, load_p=case.load_p, gen_p_max=case.gen_p_max, seed=0)
    else:
        class EndsSome(TensorDictModuleBase):  # next state = state (time index advanced by the env), reward -t
            in_keys, out_keys = ["state", "action"], ["next_state", "reward", "terminated"]

            def __init__(self):
                super().__init__()
                self.t = 0

            def forward(self, td):
                self.t += 1
                ends = torch.tensor([self.t == 7, False, self.t == 30]).unsqueeze(1)
                return td.update({"next_state": td["state"].clone(), "reward": torch.full((3, 1), -0.01 * self.t),
                                  "terminated": ends})

        def make():
            return SurrogateEnv(EndsSome(), 3, sim=simulator("anm6_easy"), seed=0)
    env = make()
    states = draw_initial_states(3, 5, env.sim, env.init)
    torch.manual_seed(1)
    policy = make_ppo_models(env)[0]
    built = []
    build = policy.build_dist_from_params
    policy.build_dist_from_params = lambda params: built.append(1) or build(params)
    got = evaluate_policy(policy, states, max_steps=60, env=env)
    assert len(built) == 1  # the distribution of the first step only: its transform wrote the other 59 actions
    del policy.build_dist_from_params
    want = _rollout_reference(policy, states, 60, make())
    if network == "surrogate":
        assert got.terminated.tolist() == [True, False, True] and got.steps.tolist() == [7, 60, 30]
    for field in ("returns", "discounted_returns", "e_loss", "penalty", "steps", "terminated"):
        # exact; the surrogate predicts no grid terms (NaN e_loss and penalty in both)
        torch.testing.assert_close(getattr(got, field), getattr(want, field), rtol=0, atol=0, equal_nan=True)


def test_evaluation_benchmark_times_both_paths_and_compares_them(tmp_path):
    """``python -m anm_torchrl.cli.bench_evaluation``: both paths timed, their metrics equal, the record written."""
    import json

    from anm_torchrl.cli import bench_evaluation

    record = bench_evaluation.main(["--network", "case33bw", "--episodes", "2", "--steps", "20", "--repeats", "1",
                                    "--out", str(tmp_path / "pass")])
    assert record["metrics_equal"] is True and record["policy"] == "pretrained:case33bw"
    assert record["best_s"]["default"] > 0 and record["best_s"]["reference"] > 0
    saved = json.loads((tmp_path / "pass.json").read_text())
    assert saved["command"].startswith("python -m anm_torchrl.cli.bench_evaluation --network case33bw")
    assert "metrics bit for bit equal: True" in (tmp_path / "pass.md").read_text()


# TorchRL's own warning: the env has no InitTracker (the noise then starts at its module's first call, on both paths)
@pytest.mark.filterwarnings("ignore:The tensordict passed to OrnsteinUhlenbeckProcessModule")
@pytest.mark.parametrize("kind", ["state_box", "previous_action", "ou_noise", "grid_counter", "reward_counter"])
def test_evaluation_carries_what_the_policy_reads_as_the_rollout_does(kind):
    """Bugs of the first versions of the env's own stepping (two reviews): an actor whose TanhNormal box is read from
    the TensorDict kept step 1's box (its transform was cached); a policy reading its previous action, an
    Ornstein-Uhlenbeck exploration module's state, a counter a policy keeps under "grid" or "reward", were not
    carried as TorchRL's step carries them. Each now equals the ``reference`` path (``env.rollout``'s) bit for bit."""
    import torch
    from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
    from torch import nn
    from torchrl.envs.utils import ExplorationType
    from torchrl.modules import OrnsteinUhlenbeckProcessModule, ProbabilisticActor, TanhNormal

    from anm_torchrl.envs import ANM6Env
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.models import make_ppo_models

    states = draw_initial_states(3, 3)
    low, high = (x.float() for x in ANM6Env(1).sim.action_bounds())
    exploration = ExplorationType.DETERMINISTIC

    class Box(nn.Module):  # the renewables' upper bound at their potential (state entries 15, 16): a moving box
        def forward(self, state):
            n = state.shape[0]
            hi = high.expand(n, 6).clone()
            hi[:, :2] = state[:, 15:17].float().clamp(min=1.0)
            return torch.zeros(n, 6), torch.full((n, 6), 0.1), low.expand(n, 6).clone(), hi

    class RateLimited(TensorDictModuleBase):  # moves at most 5 MW/MVAr a step from its previous action
        in_keys, out_keys = ["observation"], ["action"]

        def forward(self, td):
            target = torch.tensor([30.0, 50.0, 0.0, 0.0, 20.0, 0.0]).expand(td.shape[0], 6)
            prev = td.get("action", None)
            return td.set("action", torch.zeros_like(target) if prev is None else prev + (target - prev).clamp(-5, 5))

    class Counter(TensorDictModuleBase):  # keeps a step count in a key of its own (a second review's cases)
        in_keys, out_keys = ["observation"], ["action"]

        def forward(self, td):
            where = ("grid", "count") if kind == "grid_counter" else "reward"
            count = td.get(where, torch.zeros(td.shape[0], 1)) + 1
            td.set(where, count)
            return td.set("action", low + (high - low) * torch.sigmoid(count - 3))

    def make():
        if kind in ("grid_counter", "reward_counter"):
            return Counter()
        if kind == "state_box":
            return ProbabilisticActor(TensorDictModule(Box(), ["state"], ["loc", "scale", "lo", "hi"]),
                                      in_keys={"loc": "loc", "scale": "scale", "low": "lo", "high": "hi"},
                                      distribution_class=TanhNormal, distribution_kwargs={"tanh_loc": False})
        if kind == "previous_action":
            return RateLimited()
        torch.manual_seed(0)
        spec = ANM6Env(3).full_action_spec["action"]
        noise = OrnsteinUhlenbeckProcessModule(spec=spec, sigma=5.0)
        return TensorDictSequential(make_ppo_models(ANM6Env(3))[0], noise)

    if kind == "ou_noise":
        exploration = ExplorationType.RANDOM
    results = []
    for reference in (False, True):
        torch.manual_seed(7)
        results.append(evaluate_policy(make(), states, max_steps=20, env=ANM6Env(3, seed=0),
                                       exploration_type=exploration, reference=reference))
    for field in ("returns", "discounted_returns", "e_loss", "penalty", "steps", "terminated"):
        assert torch.equal(getattr(results[0], field), getattr(results[1], field)), field


def test_evaluation_resets_a_terminated_row_as_the_rollout_does(caplog):
    """A surrogate whose model ends one episode once: the evaluation resets that row as ``step_and_maybe_reset``
    does (the first version stepped it again from its last state, so the model ended it at every later step and the
    surrogate's termination warning fired: 18 terminations counted of 80 row-steps, for one)."""
    import logging

    import torch
    from tensordict.nn import TensorDictModuleBase

    from anm_torchrl.envs import SurrogateEnv
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.networks import simulator
    from anm_torchrl.training.models import make_ppo_models

    sim = simulator("anm6_easy")
    states = draw_initial_states(4, 3, sim)
    ends_at = float(states[0, -1]) + 2  # row 0 ends on its 3rd step

    class EndsOnce(TensorDictModuleBase):
        in_keys, out_keys = ["state", "action"], ["next_state", "reward", "terminated"]

        def forward(self, td):
            s = td["state"]
            ends = torch.zeros(s.shape[0], 1, dtype=torch.bool)
            ends[0, 0] = bool(s[0, -1] == ends_at)
            return td.update({"next_state": s.clone(), "reward": torch.full((s.shape[0], 1), -0.01),
                              "terminated": ends})

    counts = []
    with caplog.at_level(logging.WARNING, logger="anm_torchrl.envs.surrogate"):
        for reference in (False, True):
            env = SurrogateEnv(EndsOnce(), 4, sim=sim, seed=0, init="gym_anm")
            torch.manual_seed(0)
            result = evaluate_policy(make_ppo_models(env)[0], states, 20, env=env, reference=reference)
            assert result.steps.tolist() == [3, 20, 20, 20]
            counts.append((env.termination_watch.terminated, env.termination_watch.stepped))
    assert counts == [(1, 80), (1, 80)]
    assert not [r for r in caplog.records if "termination" in r.getMessage()]
