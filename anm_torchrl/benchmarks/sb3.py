"""Stable-Baselines3 PPO frames/s on our batched ``SB3VecEnv`` against SB3 on gym-anm itself, in one run.

Usage::

    python -m anm_torchrl.cli.bench_sb3 [--num-envs 64] [--n-steps 16] [--rollouts 16] [--gym-rollouts 1]
                                        [--threads 1] [--out results/benchmarks/bench_sb3.json]

Both sides run the same SB3 ``PPO("MlpPolicy")`` (``n_steps`` per env, batch 512, 10 epochs, CPU) over
``--num-envs`` envs: ours is :class:`~anm_torchrl.gym.sb3.SB3VecEnv` (one batched TorchRL env, numba physics);
gym-anm's is ``DummyVecEnv`` of gym-anm 2.0.1 ``ANM6Easy`` (one Python env per slot, stepped in turn). Each
side first learns one rollout (warm-up: model construction, first resets, JIT), then learns ``rollouts``
(resp. ``gym-rollouts``) more, timed: frames/s = frames / wall time of collection *and* updates, as a user sees
it. A second number splits off collection alone (SB3's ``time/fps`` counts the same). Prints one table and
writes the JSON record (machine, versions, settings, rates, ratio).
"""

from __future__ import annotations

import logging
import time
import warnings

import torch

log = logging.getLogger(__name__)


def _ppo(env, n_steps: int, seed: int):
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import Logger

    model = PPO("MlpPolicy", env, n_steps=n_steps, batch_size=512, seed=seed, device="cpu", verbose=0)
    model.set_logger(Logger(None, []))  # SB3's default logger makes an empty /tmp/SB3-<time> folder per learn()
    return model


def _bench(make_env, name: str, num_envs: int, n_steps: int, rollouts: int, seed: int) -> dict:
    """Warm up with one rollout, then time ``rollouts`` rollouts of PPO.learn; frames and seconds."""
    from stable_baselines3.common.callbacks import BaseCallback

    class CollectTimer(BaseCallback):
        """Wall time spent collecting (between rollout start and end) — the rest of learn() is updates."""

        def __init__(self):
            super().__init__()
            self.collect, self._t0 = 0.0, 0.0

        def _on_rollout_start(self) -> None:
            self._t0 = time.perf_counter()

        def _on_rollout_end(self) -> None:
            self.collect += time.perf_counter() - self._t0

        def _on_step(self) -> bool:
            return True

    frames = num_envs * n_steps
    t0 = time.perf_counter()
    model = _ppo(make_env(), n_steps, seed)
    model.learn(total_timesteps=frames)
    warm = time.perf_counter() - t0
    timer = CollectTimer()
    t0 = time.perf_counter()
    model.learn(total_timesteps=frames * rollouts, reset_num_timesteps=False, callback=timer)
    wall = time.perf_counter() - t0
    return {"impl": name, "num_envs": num_envs, "frames": frames * rollouts, "warmup_s": warm, "wall_s": wall,
            "frames_per_s": frames * rollouts / wall, "collect_s": timer.collect,
            "collect_frames_per_s": frames * rollouts / timer.collect}


def run(num_envs: int = 64, n_steps: int = 16, rollouts: int = 16, gym_rollouts: int = 1, threads: int = 1,
        seed: int = 0, command: str = "python -m anm_torchrl.cli.bench_sb3") -> dict:
    """Measure both sides in this process; returns the record (``command``: the command line that made it)."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    from anm_torchrl.provenance import machine_info, versions
    from anm_torchrl.gym.sb3 import SB3VecEnv

    torch.set_num_threads(threads)

    def gym_anm_env():
        warnings.filterwarnings("ignore", module="gym_anm")
        from gym_anm.envs import ANM6Easy

        return DummyVecEnv([ANM6Easy] * num_envs)

    ours = _bench(lambda: SB3VecEnv(num_envs=num_envs, seed=seed), "anm_torchrl SB3VecEnv", num_envs, n_steps,
                  rollouts, seed)
    theirs = _bench(gym_anm_env, "gym-anm 2.0.1 ANM6Easy in DummyVecEnv", num_envs, n_steps, gym_rollouts, seed)
    return {"command": command, "settings": {
                "num_envs": num_envs, "n_steps": n_steps, "batch_size": 512, "n_epochs": 10, "rollouts": rollouts,
                "gym_rollouts": gym_rollouts, "torch_threads": threads, "seed": seed},
            "rows": [ours, theirs], "ratio_frames_per_s": ours["frames_per_s"] / theirs["frames_per_s"],
            "ratio_collect_frames_per_s": ours["collect_frames_per_s"] / theirs["collect_frames_per_s"],
            "machine": machine_info(), "versions": versions()}


def table(record: dict) -> str:
    """The record as one markdown table."""
    lines = ["| env | envs | frames timed | PPO frames/s (collect + update) | collection alone frames/s | warm-up s |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in record["rows"]:
        lines.append(f"| {r['impl']} | {r['num_envs']} | {r['frames']:,} | {r['frames_per_s']:,.0f} | "
                     f"{r['collect_frames_per_s']:,.0f} | {r['warmup_s']:.1f} |")
    lines.append(f"\nratio: {record['ratio_frames_per_s']:.1f}x (PPO), {record['ratio_collect_frames_per_s']:.1f}x "
                 "(collection)")
    return "\n".join(lines)


if __name__ == "__main__":  # run by name, this library module would otherwise exit 0 having done nothing
    raise SystemExit("the Stable-Baselines3 comparison's command line is python -m anm_torchrl.cli.bench_sb3 "
                     "(--help lists its options)")
