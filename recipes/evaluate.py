"""Evaluate a training checkpoint (any algorithm: PPO, SAC, ...) or a baseline on the true simulator or on the
original gym-anm package.

    python recipes/evaluate.py checkpoint=outputs/ppo/.../checkpoints/best.pt
    python recipes/evaluate.py checkpoint=... env=gym_anm episodes=2 steps=3000
    python recipes/evaluate.py policy=do_nothing
    python recipes/evaluate.py policy=mpc_perfect policy_kwargs.horizon=32 episodes=4
    python recipes/evaluate.py checkpoint=... render=true steps=96   # + episode/ppo.png and episode/ppo.gif

Options are Hydra overrides (``key=value``) of ``recipes/conf_evaluate/evaluate.yaml``, composed by Hydra's compose API like
the other recipes' configs (an unknown key or a value out of range fails before anything runs; ``--help`` lists
them; no run directory: ``output=`` and ``render_dir=`` say where files go). By default the episodes start from the **test** states
(``seed=0``, the PPO recipe's ``eval.test_seed``), never from the validation states its model selection used. Both
envs (``env=exact``, the batched true simulator of the network, and ``env=gym_anm``) run the same episodes:
``episodes`` initial states drawn from the network's reset distribution with ``seed``
(:func:`anm_torchrl.evaluation.draw_initial_states`), set into ``ANMEnv`` with
``reset(..., set_state=True)`` and into gym-anm through its ``init_state`` hook. The policy acts
deterministically; an episode ends at ``steps`` or at its first termination.

The LAST line of stdout is one JSON object, printed before ``output=`` is written (so a failed write loses
nothing; it is then an error, exit status 1): ``return``, ``discounted_return``, ``e_loss``, ``penalty``, ``steps``,
``terminated`` (means over episodes; ``terminated`` is the fraction that terminated), plus ``episodes``, ``env``,
``policy``, ``checkpoint``, ``seed``, ``max_steps``, ``gamma``, ``wall_time`` (s) and ``per_episode`` lists.
With ``render=true`` the first episode is then replayed on the true simulator and drawn
(:func:`anm_torchrl.render.render_episode`): ``<render_dir>/<policy>.png`` (network at chosen times + time series)
and ``<render_dir>/<policy>.gif`` (the network over the episode); their paths go to stderr.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from omegaconf import OmegaConf

from anm_torchrl.strict_json import json_text

CONFIG = Path(__file__).parent / "conf_evaluate" / "evaluate.yaml"  # not in conf/: "checkpoint" and "env"
# are keys here but config groups there


def usage() -> str:
    """``--help``: the docstring's examples and every option with its comment from ``evaluate.yaml``."""
    return (f"{__doc__.strip()}\n\nOptions (key=value; defaults and meanings from {CONFIG.name}):\n\n"
            + CONFIG.read_text())


def parse_args(argv: list[str]):
    """The config of ``evaluate.yaml`` composed by Hydra with ``key=value`` overrides (``policy_kwargs.*`` keys are
    free, every other key must exist); raises SystemExit with a message."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    from anm_torchrl.baselines.names import available_baselines
    from anm_torchrl.training.config_checks import check_evaluate_config
    from anm_torchrl.training.recipe_errors import check_writable, user_errors

    if any(a in ("-h", "--help") for a in argv):
        print(usage())
        raise SystemExit(0)
    bad = [a for a in argv if "=" not in a]
    keys = sorted(OmegaConf.load(CONFIG).keys())
    if bad:
        raise SystemExit(f"evaluate.py: arguments must be key=value, got {bad}; keys: {keys}")
    # policy_kwargs is an open dict: its keys are the baseline's arguments (Hydra's "+" adds a key)
    overrides = [("+" + a if a.startswith("policy_kwargs.") else a) for a in argv]
    try:
        with initialize_config_dir(config_dir=str(CONFIG.parent), version_base="1.3", job_name="evaluate"):
            cfg = compose(config_name=CONFIG.stem, overrides=overrides)
    except HydraException as err:
        first = str(err).strip().splitlines()[0]
        raise SystemExit(f"evaluate.py: unknown option or bad value ({first}); valid keys: {keys}") from None
    with user_errors("evaluate.py"):
        check_evaluate_config(cfg)
        if cfg.render:  # now, not after the evaluation (output= is written after the JSON is printed)
            check_writable(cfg.render_dir, "render_dir")
    if cfg.env == "anm6":  # the former name of the exact simulator on any network
        cfg.env = "exact"
    if cfg.policy is None and cfg.checkpoint is None:
        raise SystemExit("evaluate.py: give checkpoint=<path> or policy=<baseline> "
                         f"(baselines: {', '.join(available_baselines())})")
    if cfg.policy is not None and cfg.checkpoint is not None:
        raise SystemExit("evaluate.py: give either checkpoint=... or policy=..., not both")
    if cfg.policy is not None and cfg.policy not in available_baselines():
        raise SystemExit(f"evaluate.py: policy must be one of {available_baselines()}, got {cfg.policy!r}")
    return cfg


def main(argv: list[str] | None = None) -> dict:
    cfg = parse_args(sys.argv[1:] if argv is None else argv)
    import torch

    torch.set_num_threads(int(cfg.threads))

    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.training.checkpoint import load_checkpoint, load_actor
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy, evaluate_policy_gym_anm
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.recipe_errors import user_errors

    ckpt = None
    if cfg.checkpoint is not None:
        from anm_torchrl.policies import resolve

        try:
            ckpt = load_checkpoint(resolve(cfg.checkpoint))  # pretrained:<name>: a shipped, hash-checked policy
        except (ValueError, FileNotFoundError) as err:
            raise SystemExit(f"evaluate.py: {err}") from None
    network = network_of(cfg, ckpt)
    if cfg.env == "gym_anm" and network != "anm6_easy":
        from anm_torchrl.training.config_checks import gym_anm_only

        raise SystemExit(f"evaluate.py: {gym_anm_only('env', network)} (this policy's network)")
    test_episodes, test_seed, test_steps, test_gamma = test_protocol(ckpt, network)
    cfg.seed = test_seed if cfg.seed is None else cfg.seed
    cfg.gamma = test_gamma if cfg.gamma is None else cfg.gamma
    cfg.steps = test_steps if cfg.steps is None else cfg.steps
    episodes = int(cfg.episodes) if cfg.episodes is not None else (test_episodes if cfg.env == "exact" else 2)
    with user_errors("evaluate.py"):  # a network file that exists but is not a valid network: one line
        env = make_true_env(episodes, network=network, seed=int(cfg.seed))  # states from its reset distribution
    states = draw_initial_states(episodes, int(cfg.seed), env.sim, env.init)
    if ckpt is not None:
        with user_errors("evaluate.py"):  # a checkpoint of a network file rewritten since: one line
            policy, name = load_actor(ckpt, env=make_true_env(1, network=network)), ckpt["algorithm"]
    else:
        kwargs = OmegaConf.to_container(cfg.policy_kwargs, resolve=True)
        if cfg.policy == "random":
            kwargs.setdefault("seed", int(cfg.seed))
        if cfg.policy == "optimal":  # its plan spans the episode evaluated, not the default T = 3,000
            kwargs.setdefault("horizon", int(cfg.steps))
            kwargs.setdefault("gamma", float(cfg.gamma))
        with user_errors("evaluate.py"):  # a policy_kwargs value the baseline refuses: one line, before the run
            policy, name = make_baseline(cfg.policy, env.sim, **kwargs), cfg.policy

    t0 = time.perf_counter()
    if cfg.env == "exact":
        result = evaluate_policy(policy, states, max_steps=int(cfg.steps), gamma=float(cfg.gamma), env=env)
    else:
        result = evaluate_policy_gym_anm(policy, states, max_steps=int(cfg.steps), gamma=float(cfg.gamma),
                                         progress=bool(cfg.progress))
    out = {**result.metrics(), "episodes": episodes, "env": cfg.env, "network": network, "policy": name,
           "checkpoint": None if cfg.checkpoint is None else str(cfg.checkpoint), "seed": int(cfg.seed),
           "max_steps": int(cfg.steps), "gamma": float(cfg.gamma), "wall_time": time.perf_counter() - t0,
           "per_episode": {"return": result.returns.tolist(), "discounted_return": result.discounted_returns.tolist(),
                           "steps": result.steps.tolist(), "terminated": result.terminated.tolist()}}
    line = json_text(out)
    sys.stderr.flush()
    print(line, flush=True)  # first: a failed write below must not lose a (possibly long) evaluation
    if cfg.output:
        write_output(Path(cfg.output), line)
    if cfg.render:
        from anm_torchrl.render import render_episode

        title = f"{name} on {network}, initial state 0 of seed {int(cfg.seed)}"
        if ckpt is None:  # a fresh baseline: the evaluation advanced a stateful one (random's generator)
            policy = make_baseline(cfg.policy, env.sim, **kwargs)
            if cfg.policy == "random" and episodes > 1:  # its draws for a batch of 1 are not episode 0's
                title += f" (a draw of its own, random seed {kwargs['seed']})"
        with user_errors("evaluate.py"):
            paths = render_episode(policy, make_true_env(1, network=network), states[0], int(cfg.steps),
                                   cfg.render_dir, stem=name, title=title)
        print("episode figure: " + ", ".join(str(p) for p in paths.values()), file=sys.stderr, flush=True)
    return out


def network_of(cfg, ckpt: dict | None) -> str:
    """The network to evaluate on: ``network=``, else the checkpoint's (ANM6-Easy for checkpoints that predate the
    key and for baselines); a checkpoint trained on another network than ``network=`` is refused (a network file
    given where the checkpoint names another file: by the network's key, so a moved or copied file is accepted)."""
    from anm_torchrl.networks.user import is_network_file

    def same(a: str, b: str) -> bool:  # a network file may be spelled relative here, absolute in the checkpoint
        if is_network_file(a) and is_network_file(b):
            # moved or copied since: the checkpoint's network key decides (load_actor checks it)
            return ckpt.get("network_key") is not None or Path(a).resolve() == Path(b).resolve()
        return a == b

    trained = (ckpt["config"].get("network") or "anm6_easy") if ckpt is not None else None
    if cfg.network is not None and trained is not None and not same(cfg.network, trained):
        raise SystemExit(f"evaluate.py: the checkpoint was trained on network={trained!r}, not {cfg.network!r}")
    return cfg.network or trained or "anm6_easy"


def test_protocol(ckpt: dict | None, network: str) -> tuple[int, int, int, float]:
    """``(episodes, seed, steps, gamma)`` of the test episodes figures are reported on: the checkpoint's run's
    (``eval.test_episodes``, ``eval.test_seed``, ``eval.test_max_steps``, ``eval.gamma``), or for a baseline the
    network's protocol (``recipes/conf/per_network_eval.yaml``, as a training run on ``network`` would get it)."""
    if ckpt is not None:
        ev = ckpt["config"].get("eval", {})
    else:
        from anm_torchrl.training.network_defaults import compose_recipe_config

        ev = OmegaConf.to_container(compose_recipe_config([f"network={network}"])[0].eval, resolve=True)
    steps = ev.get("test_max_steps") or ev.get("max_steps", 3000)
    from anm_torchrl.evaluation import EVAL_GAMMA

    return int(ev.get("test_episodes", 16)), int(ev.get("test_seed", 0)), int(steps), float(ev.get("gamma", EVAL_GAMMA))


def write_output(path: Path, line: str) -> None:
    """Write the JSON line to ``path`` (atomically, creating its folder); raises SystemExit naming the file."""
    from anm_torchrl.artifacts import atomic_write

    try:
        atomic_write(path, (line + "\n").encode())
    except OSError as err:
        raise SystemExit(f"evaluate.py: the result is printed above but could not be written to output={path}: "
                         f"{err}") from None


if __name__ == "__main__":
    main()
