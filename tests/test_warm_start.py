"""A PPO run started from another run's networks (``checkpoint.init_from``, tiny in-process runs on ANM6-Easy): it
begins with the source's actor (its validation pass at frame 0 is the source's own result on the same states) and
critic (values rescaled to the run's reward scale), and refuses a source of another family or architecture, a
checkpoint without reward scale, an algorithm that cannot start from another run, and ``resume`` beside it."""

from __future__ import annotations

import pytest
import torch

from anm_torchrl.training.checkpoint import load_checkpoint, save_checkpoint
from anm_torchrl.training.protocol import train
from tests.test_recipes_ppo import TINY
from tests.test_recipes_sac import TINY_SAC
from tests.test_recipes_shac import TINY_SHAC

CELLS = ["model.actor_cells=[16]", "model.critic_cells=[16]"]
PPO = [*TINY, *CELLS, "logger.backend=null", "eval.patience=null"]


def _cfg(config: str, *overrides):
    from recipe_utils import compose

    return compose(config, list(overrides))


@pytest.fixture(scope="module")
def shac_best(tmp_path_factory):
    """best.pt of a tiny SHAC run through the exact model (64 model frames)."""
    run = tmp_path_factory.mktemp("shac")
    train(_cfg("shac", *TINY_SHAC, "logger.backend=null"), run)
    return run / "checkpoints" / "best.pt"


def test_ppo_starts_from_a_shac_runs_actor_and_critic(shac_best, tmp_path):
    source = load_checkpoint(shac_best)
    summary = train(_cfg("config", *PPO, f"checkpoint.init_from={shac_best}"), tmp_path)
    first = summary["curve"][0]
    # the same deterministic actor on the same validation states (both runs' eval.seed, 10 steps): the same score
    assert (first["frames"], first["update"]) == (0, 0)
    assert first["validation"] == source["best_eval"]["discounted_return"]
    assert summary["init_from"] == {"path": str(shac_best), "algorithm": "shac", "frames": source["frames"]}
    assert summary["frames"] == 64 and len(summary["curve"]) == 3  # the start, then two updates of 32 frames
    # the start competes for best.pt: the best of the three points is what best.pt holds
    best = max(summary["curve"], key=lambda p: p["validation"])
    assert load_checkpoint(tmp_path / "checkpoints" / "best.pt")["frames"] == best["frames"]
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["reward_scale"] == summary["reward_scale"][
        "reward_scale"]


def test_the_critic_is_the_sources_in_the_runs_reward_units(shac_best):
    from anm_torchrl.training.algorithms.ppo import model_options
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.models import make_ppo_models
    from anm_torchrl.training.algorithms.base import load_networks

    source = load_checkpoint(shac_best)
    cfg = _cfg("config", *PPO)
    env = make_true_env(4, "cpu", seed=0, network="anm6_easy")
    actor, critic, _ = make_ppo_models(env, **model_options(cfg))
    src_actor, src_critic, _ = make_ppo_models(env, **model_options(cfg))
    src_actor.load_state_dict(source["actor"])
    src_critic.load_state_dict(source["state"]["critic"])
    load_networks(source, actor, critic, reward_scale=0.01, loss=cfg.loss)
    td = env.reset()
    ratio = 0.01 / source["reward_scale"]
    assert ratio != pytest.approx(1.0)  # SHAC's auto scale (~0.23 on ANM6-Easy) against PPO's 0.01: a real rescale
    torch.testing.assert_close(critic(td.clone())["state_value"], src_critic(td.clone())["state_value"] * ratio)
    torch.testing.assert_close(actor(td.clone())["loc"], src_actor(td.clone())["loc"])


def test_a_critic_of_another_discount_is_not_taken(shac_best, caplog):
    from anm_torchrl.training.algorithms.ppo import model_options
    from anm_torchrl.training.factory import make_true_env
    from anm_torchrl.training.models import make_ppo_models
    from anm_torchrl.training.algorithms.base import load_networks

    source = load_checkpoint(shac_best)
    cfg = _cfg("config", *PPO, "loss.gamma=0.9")  # SHAC's 0.995: its values are of another return
    actor, critic, _ = make_ppo_models(make_true_env(4, "cpu", seed=0, network="anm6_easy"), **model_options(cfg))
    fresh = {k: v.clone() for k, v in critic.state_dict().items()}
    load_networks(source, actor, critic, reward_scale=0.01, loss=cfg.loss)
    assert "the critic starts fresh" in caplog.text
    assert all(torch.equal(v, fresh[k]) for k, v in critic.state_dict().items())
    assert all(torch.equal(v, source["actor"][k]) for k, v in actor.state_dict().items())


def test_the_start_is_tracked_on_the_test_states_like_every_point(shac_best, tmp_path):
    summary = train(_cfg("config", *PPO, "eval.track_test=true", f"checkpoint.init_from={shac_best}"), tmp_path)
    assert summary["curve"][0]["frames"] == 0 and all("test" in point for point in summary["curve"])


def test_an_architecture_that_differs_is_named(shac_best, tmp_path):
    with pytest.raises(ValueError, match=r"model.actor_cells: checkpoint \[16\], this run \[32\]"):
        train(_cfg("config", *PPO, "model.actor_cells=[32]", f"checkpoint.init_from={shac_best}"), tmp_path)


def test_a_checkpoint_without_reward_scale_is_refused(shac_best, tmp_path):
    old = {k: v for k, v in load_checkpoint(shac_best).items() if k != "reward_scale"}
    save_checkpoint(tmp_path / "old.pt", old)
    with pytest.raises(ValueError, match="records no reward scale"):
        train(_cfg("config", *PPO, f"checkpoint.init_from={tmp_path / 'old.pt'}"), tmp_path / "run")


def test_another_family_and_an_algorithm_without_warm_starts_are_refused(shac_best, tmp_path):
    sac_dir = tmp_path / "sac"
    train(_cfg("sac", *TINY_SAC, "logger.backend=null"), sac_dir)
    with pytest.raises(ValueError, match="its networks are sac's, another family than ppo's"):
        train(_cfg("config", *PPO, f"checkpoint.init_from={sac_dir / 'checkpoints' / 'best.pt'}"), tmp_path / "a")
    with pytest.raises(ValueError, match="a sac run cannot start from another run's networks"):
        train(_cfg("sac", *TINY_SAC, "logger.backend=null", f"checkpoint.init_from={shac_best}"), tmp_path / "b")
    with pytest.raises(ValueError, match="a shac run cannot start from another run's networks"):
        train(_cfg("shac", *TINY_SHAC, "logger.backend=null", f"checkpoint.init_from={shac_best}"), tmp_path / "c")
    assert not (tmp_path / "a" / "summary.json").exists()  # refused before any training


SHAC_BRIEF = "warm_start.overrides=['collector.total_frames=64','loss.horizon=8','env.num_envs=4','eval.interval=1']"


def test_the_recipe_trains_its_warm_start_first_and_counts_its_time(tmp_path):
    """``python recipes/ppo.py warm_start.algorithm=shac``: SHAC into <run>/warm_start, PPO from its best.pt."""
    import json

    from tests.test_recipes_ppo import PPO as PPO_RECIPE, run

    run_dir = tmp_path / "run"
    run(PPO_RECIPE, *TINY, *CELLS, "logger.backend=csv", "warm_start.algorithm=shac", SHAC_BRIEF,
        f"hydra.run.dir={run_dir}", cwd=tmp_path)
    summary = json.loads((run_dir / "summary.json").read_text())
    teacher = json.loads((run_dir / "warm_start" / "summary.json").read_text())
    ws = summary["warm_start"]
    assert ws["algorithm"] == "shac" and ws["model_frames"] == teacher["model_frames"] == 64
    assert ws["checkpoint"] == str(run_dir / "warm_start" / "checkpoints" / "best.pt") == summary["init_from"]["path"]
    # the teacher's validation and test states are the PPO run's: its best policy scores the same at PPO's frame 0
    assert summary["curve"][0]["validation"] == teacher["best_eval"]["discounted_return"]
    assert teacher["config"]["eval"]["num_episodes"] == summary["config"]["eval"]["num_episodes"] == 2
    # PPO's architecture, not SHAC's ANM6-Easy entry (time features through the exact model)
    assert teacher["config"]["model"]["time_features"] is False
    assert teacher["config"]["model"]["dynamics"] == "exact"  # surrogate=none: through the exact simulator
    assert summary["wall_time"] > teacher["wall_time"] == ws["wall_time"]


@pytest.mark.parametrize("args, message", [
    (["warm_start.algorithm=sac"], "warm_start.algorithm must be null or shac, got 'sac'"),
    (["warm_start.algorithm=shac", "surrogate=lr"], "surrogate=lr has no gradients to train through"),
    (["warm_start.algorithm=shac", "checkpoint.init_from=x.pt"], "warm_start.algorithm=shac and checkpoint.init_from"),
    (["warm_start.algorithm=shac", "warm_start.overrides=['model.actor_cells=[8]','eval.num_episodes=3']"],
     r"warm_start.overrides sets eval.num_episodes, model.actor_cells: the warm start takes these from the PPO run"),
    (["warm_start.algorithm=shac", "warm_start.overrides=['loss.horizn=8']"],
     r"warm_start.overrides=\['loss.horizn=8'\]: Could not override 'loss.horizn'"),
])
def test_a_bad_warm_start_is_one_line(args, message, tmp_path):
    import re

    from tests.test_recipes_ppo import PPO as PPO_RECIPE, run

    (tmp_path / "x.pt").write_bytes(b"")
    proc = run(PPO_RECIPE, *TINY, *args, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, check=False)
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode != 0 and re.search(message, last), proc.stderr[-2000:]


def test_train_itself_runs_the_warm_start(tmp_path):
    """A programmatic caller (a study's cell composing the recipe's config) gets what the recipe does, and its
    config is left as composed (a study compares it with the cell's)."""
    cfg = _cfg("config", *PPO, "warm_start.algorithm=shac", SHAC_BRIEF)
    summary = train(cfg, tmp_path)
    assert cfg.checkpoint.init_from is None and summary["config"]["checkpoint"]["init_from"] is None
    assert summary["warm_start"]["model_frames"] == 64 and (tmp_path / "warm_start" / "summary.json").is_file()
    assert summary["init_from"]["path"] == summary["warm_start"]["checkpoint"]


def test_the_main_jobs_entry_and_the_studies_plain_ppo():
    from anm_torchrl.experiments.ppo_runs import ppo_overrides
    from anm_torchrl.training.network_defaults import compose_recipe_config

    cfg, defaults = compose_recipe_config(["surrogate=pinn"])  # ANM6-Easy's entry: SHAC first, PPO at lr 1e-5
    assert cfg.warm_start.algorithm == "shac" and cfg.optim.lr == 1e-5 and defaults["applied"]["optim.lr"] == 1e-5
    cfg, _ = compose_recipe_config(["surrogate=pinn", "optim.lr=3e-5"])  # the command line's lr wins
    assert cfg.warm_start.algorithm == "shac" and cfg.optim.lr == 3e-5
    cfg, _ = compose_recipe_config(["surrogate=pinn", "warm_start.algorithm=null"])  # no warm start: PPO's own lr
    assert cfg.optim.lr == 1e-4
    cfg, _ = compose_recipe_config(["surrogate=none"])
    assert cfg.warm_start.algorithm is None and cfg.optim.lr == 1e-4
    # networks given on the command line: no warm start of the entry, PPO at the warm start's lr
    cfg, _ = compose_recipe_config(["surrogate=pinn", "checkpoint.init_from=/a/best.pt"])
    assert cfg.warm_start.algorithm is None and cfg.optim.lr == 1e-5
    # the paper's experiments and the payoff study compare PPO from fresh networks on every training env
    cfg, _ = compose_recipe_config(ppo_overrides({"name": "pinn"}, 0, {}))
    assert cfg.warm_start.algorithm is None and cfg.optim.lr == 1e-4


def test_a_resumed_warm_started_run_keeps_its_warm_start_and_does_not_train_it_again(tmp_path):
    first = train(_cfg("config", *PPO, "warm_start.algorithm=shac", SHAC_BRIEF), tmp_path / "a")
    teacher_mtime = (tmp_path / "a" / "warm_start" / "summary.json").stat().st_mtime_ns
    resumed = train(_cfg("config", *PPO, "warm_start.algorithm=shac", SHAC_BRIEF, "collector.total_frames=96",
                         f"checkpoint.resume={tmp_path / 'a' / 'checkpoints' / 'last.pt'}"), tmp_path / "b")
    assert not (tmp_path / "b" / "warm_start").exists()  # not trained again
    assert (tmp_path / "a" / "warm_start" / "summary.json").stat().st_mtime_ns == teacher_mtime
    assert resumed["warm_start"] == first["warm_start"] and resumed["frames"] == 96
    assert resumed["wall_time"] > first["wall_time"] > first["warm_start"]["wall_time"]
