"""How long a validation pass takes: :func:`anm_torchrl.evaluation.evaluate_policy` on its default path (the
package's env stepped through its ``_step``, the actor's deterministic action from its distribution's transform)
against its ``reference`` path (TorchRL's ``env.step_and_maybe_reset`` and the policy's own call, as
``env.rollout``), measured alternately in one run, with their metrics compared bit for bit.

The policy is the network's shipped one (``pretrained:<network>``, an actor of the recipes' kind) where there is
one, else a seeded untrained PPO actor; the states are the network's validation states (``eval.seed`` 1), as many
and as long as its validation protocol's passes unless given.
"""

from __future__ import annotations

import time

import torch

from anm_torchrl.benchmarks.timing import record_provenance, write_record

FIELDS = ("returns", "discounted_returns", "e_loss", "penalty", "steps", "terminated")


def _policy(network: str, env):
    from anm_torchrl.policies import available_pretrained, pretrained_path
    from anm_torchrl.training.checkpoint import load_actor
    from anm_torchrl.training.models import make_ppo_models

    if network in available_pretrained():
        return load_actor(pretrained_path(network), env=env), f"pretrained:{network}"
    torch.manual_seed(0)
    return make_ppo_models(env)[0], "untrained PPO actor (seed 0)"


def measure(network: str = "anm6_easy", episodes: int | None = None, steps: int | None = None,
            repeats: int = 3) -> dict:
    """Seconds of one pass on each path (the best of ``repeats``, the paths alternated) and whether their metrics
    are equal; ``episodes`` / ``steps`` default to the network's validation protocol."""
    from anm_torchrl.evaluation import EVAL_GAMMA, draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.network_defaults import compose_recipe_config

    torch.set_num_threads(1)
    protocol = compose_recipe_config([f"network={network}"])[0].eval  # the PPO recipe's validation protocol
    episodes = int(protocol["num_episodes"] if episodes is None else episodes)
    steps = int(protocol["max_steps"] if steps is None else steps)
    env = make_true_env(episodes, network=network, seed=int(protocol["seed"]))
    states = draw_initial_states(episodes, int(protocol["seed"]), env.sim, env.init)
    policy, name = _policy(network, make_true_env(1, network=network))
    policy.eval()
    evaluate_policy(policy, states, max_steps=min(steps, 50), env=env)  # warm-up (numba, caches)
    seconds = {"default": [], "reference": []}
    results = {}
    for _ in range(repeats):
        for path in seconds:
            t0 = time.perf_counter()
            results[path] = evaluate_policy(policy, states, max_steps=steps, gamma=EVAL_GAMMA, env=env,
                                            reference=path == "reference")
            seconds[path].append(time.perf_counter() - t0)
    equal = all(torch.equal(getattr(results["default"], f), getattr(results["reference"], f)) for f in FIELDS)
    best = {path: min(s) for path, s in seconds.items()}
    return {"network": network, "policy": name, "episodes": episodes, "steps": steps, "repeats": repeats,
            "seconds": seconds, "best_s": best, "speedup": best["reference"] / best["default"],
            "metrics_equal": equal, "discounted_return": results["default"].metrics()["discounted_return"],
            "threads": 1}


def markdown(record: dict) -> list[str]:
    """The table of :func:`measure`'s record."""
    cpu = (record.get("machine") or {}).get("cpu", "this machine")
    return [f"A validation pass of `evaluate_policy` on {record['network']} ({record['episodes']} states x "
            f"{record['steps']:,} steps, {record['policy']}, 1 thread, {cpu}); best of {record['repeats']}, the "
            "paths alternated", "", "| path | seconds per pass |", "|---|---:|",
            f"| default (the env's `_step`, the actor's transform) | {record['best_s']['default']:.2f} |",
            f"| reference (`env.step_and_maybe_reset`, `policy(td)`) | {record['best_s']['reference']:.2f} |", "",
            f"speed-up {record['speedup']:.2f}x; metrics bit for bit equal: {record['metrics_equal']} (discounted "
            f"return {record['discounted_return']:.6g})"]


def run(network: str, episodes: int | None, steps: int | None, repeats: int, out: str | None,
        argv: list[str] | None = None) -> dict:
    """:func:`measure`, with the command's provenance; written to ``<out>.json`` / ``<out>.md`` if ``out``."""
    record = {**measure(network, episodes, steps, repeats),
              **record_provenance("anm_torchrl.cli.bench_evaluation", argv)}
    if out:
        write_record(out, record, markdown(record))
    return record


if __name__ == "__main__":  # run by name, this library module would otherwise exit 0 having done nothing
    raise SystemExit("the evaluation benchmark's command line is python -m anm_torchrl.cli.bench_evaluation "
                     "(--help lists its options)")
