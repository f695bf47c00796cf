"""What an algorithm takes from its config on resume and at the end of its budget: the optimisers' rates given on
the command line, SHAC's staggered rows, SHAC's PINN options from the ``surrogate`` group, and SHAC's exact
model-frame budget. In-process and tiny: algorithms built from composed configs, no recipe subprocess."""

from __future__ import annotations

import json

import pytest
import torch

from tests.test_recipes_ppo import TINY
from tests.test_recipes_sac import TINY_SAC
from tests.test_recipes_shac import TINY_SHAC

NO_WORKER = "loss.critic_worker=false"
CONFIGS = {"ppo": ("config", TINY), "sac": ("sac", TINY_SAC), "shac": ("shac", [*TINY_SHAC, NO_WORKER])}


def _build(algorithm: str, overrides=(), resume=None, budget: int = 0):
    """``algorithm`` on its tiny config plus ``overrides``; budget 0 by default (no collector)."""
    from recipe_utils import compose

    from anm_torchrl.training.algorithms import get_algorithm

    config, tiny = CONFIGS[algorithm]
    cfg = compose(config, [*tiny, *overrides])
    return get_algorithm(algorithm)(cfg, device=torch.device("cpu"), seed=0, budget=budget, reward_scale=1.0,
                                    resume=resume)


def _checkpoint(algo, frames: int = 0) -> dict:
    """What the protocol saves of ``algo`` and hands back as ``resume``."""
    return {"actor": algo.actor.state_dict(), "obs_norm": algo.normalizer.stats(), "state": algo.state_dict(),
            "frames": frames, "update": 1}


def _optimizers(algo) -> list[tuple[str, torch.optim.Optimizer, bool]]:
    """The algorithm's optimisers: (config key of its rate, optimiser, whether it takes optim.eps/weight_decay)."""
    if algo.name == "ppo":
        return [("lr", algo.optim, True)]
    if algo.name == "sac":  # the temperature's Adam takes the rate only
        return [("lr", algo.optims["actor"], True), ("lr", algo.optims["qvalue"], True),
                ("lr", algo.optims["alpha"], False)]
    return [("actor_lr", algo.actor_optim, True), ("critic_lr", algo.critic_optim, True)]


def _take_a_step(optimizers) -> None:
    """One step of each optimiser (gradients of 1), so each has a state a resume must keep."""
    for optim in optimizers:
        for group in optim.param_groups:
            for p in group["params"]:
                p.grad = torch.ones_like(p)
        optim.step()


@pytest.mark.parametrize("algorithm", ["ppo", "sac", "shac"])
def test_a_resumed_run_takes_the_optimizer_options_it_is_given(algorithm):
    """``optimizer.load_state_dict`` restores the checkpoint's lr, eps and weight decay; a resumed run with other
    values on the command line (the protocol warns they differ) uses them, and keeps Adam's moments."""
    rates = {"ppo": ["lr"], "sac": ["lr"], "shac": ["actor_lr", "critic_lr"]}[algorithm]
    old = _build(algorithm, [f"optim.{key}=0.001" for key in rates])
    _take_a_step(optim for _, optim, _ in _optimizers(old))
    new_rates = {key: 0.0002 * (i + 1) for i, key in enumerate(rates)}
    new = _build(algorithm, ["optim.eps=0.0001", "optim.weight_decay=0.01",
                             *(f"optim.{key}={lr}" for key, lr in new_rates.items())],
                 resume=_checkpoint(old, frames=32))
    try:
        for key, optim, adam_options in _optimizers(new):
            expected = {"lr": new_rates[key], **({"eps": 0.0001, "weight_decay": 0.01} if adam_options else {})}
            for group in optim.param_groups:
                assert {k: group[k] for k in expected} == pytest.approx(expected), (key, group)
            state = optim.state_dict()["state"]
            assert state and all(int(s["step"]) == 1 for s in state.values()), key  # the moments are kept
    finally:
        new.close()
        old.close()


def test_a_resumed_shac_run_staggers_its_rows_as_a_fresh_one():
    """``env.stagger``: the rows' step counters start spread over 0..max_steps-1 on resume too (the rows restart
    from fresh states, their counters are not saved); they all started at 0 (their episodes ending together)."""
    overrides = ["env.num_envs=16", "env.max_steps=24", "env.stagger=true"]
    torch.manual_seed(0)
    fresh = _build("shac", overrides)
    assert fresh.steps.unique().numel() > 1
    torch.manual_seed(1)
    resumed = _build("shac", overrides, resume=_checkpoint(fresh, frames=64))
    assert resumed.steps.unique().numel() > 1, resumed.steps
    assert bool((resumed.steps < resumed.max_steps).all())


@pytest.fixture(scope="module")
def smoke_pinn(tmp_path_factory):
    """A smoke-preset PINN of ANM6-Easy (seconds to train), saved."""
    from anm_torchrl.networks import ANM6_EASY
    from anm_torchrl.networks import simulator as network_simulator
    from anm_torchrl.surrogates.pinn import train as tr

    sim = network_simulator(ANM6_EASY)
    cfg = tr.preset("smoke")
    modules, report = tr.train_pinn(cfg, sim)
    return tr.save_pinn(tmp_path_factory.mktemp("pinn") / "pinn.safetensors", modules, cfg, report, sim)


def _pinn_model(path, *overrides: str):
    from recipe_utils import compose

    from anm_torchrl.training.algorithms.shac import PINNModel
    from anm_torchrl.training.factory import make_true_env

    cfg = compose("shac", [*TINY_SHAC, "model=pinn", "surrogate=pinn", f"surrogate.path={path}", *overrides])
    return PINNModel(make_true_env(2, network=cfg.network), cfg)


def test_shac_through_the_pinn_takes_the_surrogate_groups_terminal_options(smoke_pinn):
    """``model=pinn`` loads the chain with ``surrogate=pinn``'s options, as PPO's surrogate env does: the residual
    threshold of its physics terminal check, and the terminal decision (a classifier needs its folder)."""
    from anm_torchrl.surrogates.pinn.chain import DEFAULT_RESIDUAL_THRESHOLD, PhysicsTerminal

    def thresholds(model):
        return [m.residual_threshold for m in model.chain.modules() if isinstance(m, PhysicsTerminal)]

    assert thresholds(_pinn_model(smoke_pinn)) == [DEFAULT_RESIDUAL_THRESHOLD]
    assert thresholds(_pinn_model(smoke_pinn, "surrogate.residual_threshold=0.5")) == [0.5]
    with pytest.raises(ValueError, match="terminal='classifier' needs classifier_path"):
        _pinn_model(smoke_pinn, "surrogate.terminal=classifier")


def test_shac_counts_every_model_frame_of_its_last_rollout(tmp_path):
    """The last rollout runs ceil(remaining / rows) steps of every row (so the recorded entries re-run frame for
    frame: ANM6-Easy's 15,000,064): with 4 rows x 8 steps and a budget of 38, 32 + 4 x 2 = 40 model frames, which the
    summary reports as run (it is never cut to the budget it passed)."""
    from recipe_utils import compose

    from anm_torchrl.training.protocol import train

    cfg = compose("shac", [*TINY_SHAC, NO_WORKER, "collector.total_frames=38", "logger.backend=null",
                           "eval.interval=null"])
    summary = train(cfg, tmp_path / "run")
    assert summary["model_frames"] == 40 and summary["updates"] == 2
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["model_frames"] == 40


def test_sac_warns_when_its_actor_would_never_step(caplog):
    """A budget below ``optim.actor_delay_frames`` (100,000 on feeders and users' networks) trained only the Q
    networks, and said nothing."""
    import logging

    with caplog.at_level(logging.WARNING, logger="anm_torchrl.training.algorithms.sac"):
        _build("sac", ["optim.actor_delay_frames=1000", "collector.total_frames=96"])
    assert any("the actor never steps in this run" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="anm_torchrl.training.algorithms.sac"):
        _build("sac", ["optim.actor_delay_frames=0", "collector.total_frames=96"])
    assert not caplog.records
