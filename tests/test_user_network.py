"""A user's network by name and by file: ``register_network`` from a gym-anm dict, ``save_network`` /
``load_network_file`` (the ``.npz`` format a recipe takes as ``network=path``), the errors that name what is wrong,
and a PPO run on a network file given by a relative path."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from anm_torchrl import networks as N
from anm_torchrl.grid.identity import network_key

ROOT = Path(__file__).resolve().parents[1]
NAN = np.nan


def feeder() -> tuple[dict, np.ndarray, np.ndarray]:
    """A 4-bus radial feeder (33 kV, 10 MVA base): two loads, a PV unit with capability corners, a storage unit
    with SOC_MIN > 0; 8-step profiles (MW)."""
    bus = [[0, 0, 33, 1.0, 1.0], [1, 1, 33, 1.1, 0.9], [2, 1, 33, 1.1, 0.9], [3, 1, 33, 1.1, 0.9]]
    branch = [[0, 1, 0.01, 0.03, 0.0, 20, NAN, NAN], [1, 2, 0.02, 0.04, 0.0, 15, NAN, NAN],
              [1, 3, 0.02, 0.05, 0.0, 15, NAN, NAN]]
    dev = [[0, 0, 0, NAN, 50, -50, 50, -50, NAN, NAN, NAN, NAN, NAN, NAN, NAN],
           [1, 2, -1, 0.2, NAN, -4, NAN, NAN, NAN, NAN, NAN, NAN, NAN, NAN, NAN],
           [2, 3, -1, 0.3, NAN, -3, NAN, NAN, NAN, NAN, NAN, NAN, NAN, NAN, NAN],
           [3, 3, 2, NAN, 5, 0, 3, -3, 4, NAN, 2, -2, NAN, NAN, NAN],
           [4, 2, 3, NAN, 2, -2, 2, -2, NAN, NAN, NAN, NAN, 8, 1, 0.95]]
    t = np.arange(8)
    load_p = -np.stack([2 + np.sin(t), 1.5 + 0.5 * np.cos(t)], 1)
    gen_p_max = (4 * np.clip(np.sin(np.pi * t / 7), 0, None)).reshape(-1, 1)
    return {"baseMVA": 10, "bus": bus, "device": dev, "branch": branch}, load_p, gen_p_max


@pytest.fixture
def registered():
    net, load_p, gen_p_max = feeder()
    case = N.register_network("test_feeder", net, load_p, gen_p_max, source="tests")
    yield case
    N.unregister_network("test_feeder")


def test_register_network_by_name(registered):
    """A registered name is listed and builds the same simulator as the dict it came from."""
    from anm_torchrl.training.factory import make_env

    net, load_p, gen_p_max = feeder()
    assert "test_feeder" in N.list_networks() and registered.source == "tests"
    by_name, by_dict = N.simulator("test_feeder"), N.simulator(net, load_p, gen_p_max)
    assert network_key(by_name) == network_key(by_dict)
    env = make_env("none", network="test_feeder", num_envs=3, seed=0)
    td = env.rollout(4, break_when_any_done=False)
    assert td["next", "reward"].shape == (3, 4, 1) and bool(td["next", "reward"].isfinite().all())


def test_register_network_refuses_bad_names_and_networks(registered):
    net, load_p, gen_p_max = feeder()
    with pytest.raises(ValueError, match="already registered"):
        N.register_network("test_feeder", net, load_p, gen_p_max)
    with pytest.raises(ValueError, match="built-in network"):
        N.register_network("case33bw", net, load_p, gen_p_max)
    with pytest.raises(ValueError, match="letters, digits"):
        N.register_network("my feeder/1", net, load_p, gen_p_max)
    bad = {**net, "branch": [list(r) for r in net["branch"]]}
    bad["branch"][1][3] = -0.04
    with pytest.raises(ValueError, match=r"'branch', branch \(1, 2\), column BR_X"):
        N.register_network("other", bad, load_p, gen_p_max)
    with pytest.raises(ValueError, match="gen_p_max"):
        N.register_network("other", net, load_p, gen_p_max[:, :0])
    assert "other" not in N.list_networks()  # nothing registered on a refusal


def test_network_file_round_trip(tmp_path):
    """save_network then get_network(path): the same tables, profiles, constants and simulator identity."""
    net, load_p, gen_p_max = feeder()
    path = N.save_network(tmp_path / "feeder.npz", net, load_p, gen_p_max, gamma=0.99, source="tests")
    case = N.get_network(str(path))
    assert case.name == "feeder" and case.gamma == 0.99 and case.delta_t == 0.25 and case.source == "tests"
    np.testing.assert_array_equal(case.load_p, load_p)
    assert network_key(N.simulator(str(path))) == network_key(N.simulator(net, load_p, gen_p_max, gamma=0.99))
    assert not [p for p in tmp_path.iterdir() if p.name != "feeder.npz"]  # no temporary file left


def test_network_file_errors_name_the_file_and_the_fault(tmp_path):
    net, load_p, gen_p_max = feeder()
    with pytest.raises(ValueError, match="does not exist"):
        N.get_network(str(tmp_path / "missing.npz"))
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not an archive")
    with pytest.raises(ValueError, match="junk.npz is not a readable network file"):
        N.get_network(str(junk))
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(ValueError, match="other.npz is not an anm_torchrl network file"):
        N.get_network(str(other))
    good = N.save_network(tmp_path / "good.npz", net, load_p, gen_p_max)
    with np.load(good) as z:
        entries = dict(z)
    entries["device"] = entries["device"].copy()
    entries["device"][4, 12] = NAN  # storage without SOC_MAX
    tampered = tmp_path / "tampered.npz"
    np.savez(tampered, **entries)
    with pytest.raises(ValueError, match=r"tampered.npz: .*'device', device 4, column SOC_MAX"):
        N.get_network(str(tampered))
    with pytest.raises(ValueError, match=r"ends with \.npz"):
        N.save_network(tmp_path / "feeder.json", net, load_p, gen_p_max)
    bad = {**net, "baseMVA": -1}
    with pytest.raises(ValueError, match="baseMVA"):
        N.save_network(tmp_path / "bad.npz", bad, load_p, gen_p_max)
    assert not (tmp_path / "bad.npz").exists()  # a refused network writes nothing


def test_corrupted_network_file_entries_are_named(tmp_path):
    """Bug: a network file with a 2-number baseMVA, a meta whose env is a list or a non-integer format_version
    escaped as a raw TypeError / AttributeError / int() error not naming the file (recipes show ValueErrors only)."""
    net, load_p, gen_p_max = feeder()
    good = N.save_network(tmp_path / "good.npz", net, load_p, gen_p_max)
    with np.load(good) as z:
        entries = dict(z)
    for key, value, message in [("baseMVA", np.array([10.0, 20.0]), "baseMVA must be one number"),
                                ("meta", np.array('{"env": [0.25]}'), "unreadable meta entry"),
                                ("format_version", np.array("one"), "unreadable format_version entry")]:
        path = tmp_path / f"bad_{key}.npz"
        np.savez(path, **{**entries, key: value})
        with pytest.raises(ValueError, match=rf"bad_{key}.npz: {message}"):
            N.get_network(str(path))


def test_device_ids_and_types_must_be_integers():
    """Bug: DEV_TYPE 1.5 passed as a generator (int() truncates) and then belonged to no device kind (a contradictory
    profile-shape error); DEV_ID 2.5 beside an id 2 mapped both devices to id 2 in the observation."""
    net, load_p, gen_p_max = feeder()
    for col, value in ((2, 1.5), (0, 2.5)):
        bad = {**net, "device": [list(r) for r in net["device"]]}
        bad["device"][2][col] = value
        with pytest.raises(ValueError, match=rf"'device', row 2, column {('DEV_ID', '', 'DEV_TYPE')[col]}: "
                                             rf"must be an integer, got {value}"):
            N.simulator(bad, load_p, gen_p_max)


def test_reward_constants_numpy_scalars_and_infinities():
    """Bug: numpy scalars (np.float32 delta_t) were refused with "must be > 0, got np.float32(0.25)", while +inf
    delta_t / lamb and a bool passed (NaN rewards, or a failure at reset)."""
    net, load_p, gen_p_max = feeder()
    sim = N.simulator(net, load_p, gen_p_max, delta_t=np.float32(0.25), gamma=np.float32(0.99), lamb=np.int64(100))
    assert sim.gamma == pytest.approx(0.99) and sim.lamb == 100
    for kwargs, message in [({"delta_t": float("inf")}, "delta_t must be a finite number > 0"),
                            ({"delta_t": True}, "delta_t must be a finite number > 0"),
                            ({"lamb": float("inf")}, "lamb must be a finite number >= 0")]:
        with pytest.raises(ValueError, match=message):
            N.simulator(net, load_p, gen_p_max, **kwargs)


def test_check_network_name():
    N.check_network_name("case33bw")
    with pytest.raises(ValueError, match="unknown network 'case34bw'; registered: .*anm6_easy"):
        N.check_network_name("case34bw")
    with pytest.raises(ValueError, match="no such network file 'nowhere/feeder.npz'"):
        N.check_network_name("nowhere/feeder.npz")


def test_a_pathlib_path_names_a_network_file(tmp_path):
    """Bug: gymnasium.make(..., network=Path(file)) said "unknown network PosixPath(...)" for an existing file."""
    import gymnasium

    import anm_torchrl.gym  # noqa: F401  registers the ids

    net, load_p, gen_p_max = feeder()
    path = N.save_network(tmp_path / "feeder.npz", net, load_p, gen_p_max)
    N.check_network_name(path)
    env = gymnasium.make("anm_torchrl/ANM-v0", network=path)
    assert env.reset(seed=0)[0].shape == env.observation_space.shape


def test_ppo_recipe_takes_a_network_file(tmp_path):
    """``python recipes/ppo.py network=my_feeder.npz`` (relative to where it is typed; the run directory is
    elsewhere): trains and tests on that network, and evaluate.py takes the checkpoint's network."""
    net, load_p, gen_p_max = feeder()
    N.save_network(tmp_path / "my_feeder.npz", net, load_p, gen_p_max)
    run_dir = tmp_path / "runs" / "r"
    tiny = ["env.num_envs=4", "collector.frames_per_batch=32", "collector.total_frames=64", "eval.max_steps=8",
            "eval.num_episodes=2", "eval.test_episodes=2", "loss.mini_batch_size=16", "loss.ppo_epochs=1",
            "logger.progress=false"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "ppo.py"), *tiny, "network=my_feeder.npz",
                           f"hydra.run.dir={run_dir}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["config"]["network"] == str(tmp_path / "my_feeder.npz") and summary["frames"] == 64
    assert all(math.isfinite(summary["test"][c]["discounted_return"]) for c in ("best", "last"))
    # evaluate.py: the file spelled relative to where it is typed is the checkpoint's network (refused before)
    ckpt = run_dir / "checkpoints" / "best.pt"
    evaluate = [sys.executable, str(ROOT / "recipes" / "evaluate.py"), f"checkpoint={ckpt}", "episodes=1", "steps=4"]
    ok = subprocess.run([*evaluate, "network=my_feeder.npz"], cwd=tmp_path, env=env, capture_output=True, text=True,
                        timeout=300)
    assert ok.returncode == 0 and math.isfinite(json.loads(ok.stdout.splitlines()[-1])["return"]), ok.stderr[-2000:]
    # the file rewritten with other lines under the same name: its checkpoint is refused, naming why
    other = {**net, "branch": [list(r) for r in net["branch"]]}
    other["branch"][0][3] *= 3
    N.save_network(tmp_path / "my_feeder.npz", other, load_p, gen_p_max)
    changed = subprocess.run(evaluate, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert changed.returncode != 0 and "was trained on another network" in changed.stderr, changed.stderr[-2000:]
    assert "Traceback" not in changed.stderr
    resumed = subprocess.run([sys.executable, str(ROOT / "recipes" / "ppo.py"), *tiny, "network=my_feeder.npz",
                              f"checkpoint.resume={ckpt}", f"hydra.run.dir={tmp_path / 'runs' / 'resumed'}"],
                             cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert resumed.returncode != 0 and "was trained on another network" in resumed.stderr, resumed.stderr[-2000:]
    assert "Traceback" not in resumed.stderr and not (tmp_path / "runs" / "resumed").exists()  # one line, no run dir
    bad = subprocess.run([sys.executable, str(ROOT / "recipes" / "ppo.py"), "network=nothing.npz",
                          f"hydra.run.dir={tmp_path / 'runs' / 'bad'}"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode != 0 and "no such network file" in bad.stderr and "Traceback" not in bad.stderr


def test_training_refuses_a_network_with_nothing_to_control(tmp_path):
    """A valid network whose devices are the slack and loads only: every training recipe stops before it builds a
    surrogate or a model, naming why (a policy would have no action)."""
    net, load_p, _ = feeder()
    net = {**net, "device": [d for d in net["device"] if d[2] in (0, -1)]}
    N.save_network(tmp_path / "loads_only.npz", net, load_p, np.zeros((load_p.shape[0], 0)))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    for recipe, extra in (("ppo.py", ["surrogate=pinn"]), ("shac.py", [])):
        proc = subprocess.run([sys.executable, str(ROOT / "recipes" / recipe), "network=loads_only.npz", *extra,
                               f"hydra.run.dir={tmp_path / recipe}"], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=120)
        assert proc.returncode != 0 and "has no controllable device" in proc.stderr, proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr and not (tmp_path / recipe / "checkpoints").exists()


def _flat_q_network(tmp_path) -> tuple[Path, list[int]]:
    """:func:`feeder` with no reactive range on its PV unit (QMAX = QMIN = 0, capability corners too) nor on its
    storage unit (a battery without reactive power), saved as a user's file; and the flat entries' positions in the
    action (generators' P, Q, then storage P, Q: Q of the PV unit and Q of the storage unit)."""
    net, load_p, gen_p_max = feeder()
    devices = []
    for d in net["device"]:
        d = list(d)
        if d[2] == 2:  # the PV unit: QMAX, QMIN, Q+, Q-
            d[6] = d[7] = d[10] = d[11] = 0.0
        if d[2] == 3:  # the storage unit: QMAX, QMIN
            d[6] = d[7] = 0.0
        devices.append(d)
    return N.save_network(tmp_path / "flat_q.npz", {**net, "device": devices}, load_p, gen_p_max), [1, 3]


def test_every_algorithm_trains_where_an_action_range_is_a_single_value(tmp_path):
    """A storage unit without reactive power and a PV unit without reactive range (QMAX = QMIN = 0): gym-anm accepts
    them and asserts the action lies in its box [0, 0] there. The training recipes refused them (TorchRL's TanhNormal
    needs low < high); now each algorithm's actor writes those entries at their value and samples the others
    (``PartlyFixedTanhNormal``), its log-probability that of the sampled entries: PPO, SAC and SHAC train with finite
    losses, every collected action has the flat entries at 0, and a checkpoint scores through evaluate.py."""
    import torch

    from anm_torchrl.training.algorithms import get_algorithm
    from anm_torchrl.training.network_defaults import compose_recipe_config
    from tests.test_recipes_ppo import TINY
    from tests.test_recipes_sac import TINY_SAC
    from tests.test_recipes_shac import TINY_SHAC

    file, flat = _flat_q_network(tmp_path)
    free = [i for i in range(4) if i not in flat]
    for name, config, tiny in (("ppo", "config", TINY), ("sac", "sac", [*TINY_SAC, "collector.init_random_frames=0"]),
                               ("shac", "shac", TINY_SHAC)):
        cfg = compose_recipe_config([*tiny, f"network={file}"], config)[0]
        torch.manual_seed(0)
        algo = get_algorithm(name)(cfg, device=torch.device("cpu"), seed=0, budget=64, reward_scale=1.0, resume=None)
        try:
            frames, metrics = algo.iterate(64)
            td = algo.actor(algo.collector.env.reset() if name != "shac" else _reset(file))
        finally:
            algo.close()
        losses = {k: float(v) for k, v in metrics.items() if k.startswith("train/loss")}
        assert frames > 0 and losses and all(math.isfinite(v) for v in losses.values()), (name, metrics)
        action, log_prob = td["action"], td["action_log_prob"]
        assert (action[..., flat] == 0).all() and torch.isfinite(log_prob).all(), (name, action)
        assert action[..., free].std(0).gt(0).all(), (name, action)  # the other entries are sampled
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    run = subprocess.run([sys.executable, str(ROOT / "recipes" / "ppo.py"), "network=flat_q.npz", *TINY,
                          f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    scored = subprocess.run([sys.executable, str(ROOT / "recipes" / "evaluate.py"),
                             f"checkpoint={tmp_path / 'run' / 'checkpoints' / 'best.pt'}", "output=null"],
                            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert scored.returncode == 0, scored.stderr[-2000:]
    line = json.loads(scored.stdout.strip().splitlines()[0])
    assert line["discounted_return"] == pytest.approx(summary["test"]["best"]["discounted_return"], rel=1e-12)


def test_the_partly_fixed_distribution_scores_its_draw_as_tanh_normal_does_where_tanh_saturates():
    """A review's finding: SACLoss scores a draw through ``rsample_and_log_prob`` where a distribution has one
    (TanhNormal scores the pre-tanh value it drew); without it the fallback inverted the rounded action, wrong once
    the pre-tanh mean passes ~8 (26.77 against 20.13 at 8, +34.77 against -32.43 at 10). Both paths now give
    TanhNormal's own score of the chosen entries, and the fixed entries sit at their value."""
    import torch
    from torchrl.modules import TanhNormal
    from torchrl.objectives.sac import compute_rsample_log_prob

    from anm_torchrl.training.distributions import PartlyFixedTanhNormal

    low, high = torch.tensor([0.0, -2.0]), torch.tensor([5.0, 2.0])
    free, fixed = torch.tensor([0, 2]), torch.tensor([0.0, 0.7, 0.0, -0.3])
    for mean in (3.0, 8.0, 10.0):
        loc, scale = torch.full((16, 2), mean), torch.full((16, 2), 0.1)
        dist = PartlyFixedTanhNormal(loc, scale, low, high, free, fixed)
        torch.manual_seed(0)
        action, log_prob = compute_rsample_log_prob(dist)  # what SACLoss computes
        torch.manual_seed(0)
        chosen, expected = TanhNormal(loc, scale, low=low, high=high, tanh_loc=False).rsample_and_log_prob()
        assert torch.equal(action[:, free], chosen) and torch.equal(log_prob, expected), mean
        assert (action[:, [1, 3]] == torch.tensor([0.7, -0.3])).all()
        torch.manual_seed(0)
        sampled, sampled_lp = dist.sample_and_log_prob()
        assert torch.equal(sampled[:, free], chosen.detach()) and torch.allclose(sampled_lp, expected)


def _reset(file):
    """A reset TensorDict of 8 grids of the network in ``file`` (the true env), for the actor to act on."""
    from anm_torchrl.training.factory import make_true_env

    return make_true_env(8, "cpu", seed=0, network=str(file)).reset()


def test_the_pinn_refuses_an_action_whose_range_is_a_single_value(tmp_path):
    """Its KKT modules' training diverged on a single-value range (a traceback advising a lower lr): the PINN's
    recipes stop with one line naming the entries and what takes such a network, before training anything."""
    file, _ = _flat_q_network(tmp_path)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0", "ANM_TORCHRL_HOME": str(tmp_path / "h")}
    for recipe, extra in (("ppo.py", ["surrogate=pinn"]), ("shac.py", ["model=pinn"]),
                          ("train_pinn.py", ["pinn_preset=smoke", "path=pinn"])):
        proc = subprocess.run([sys.executable, str(ROOT / "recipes" / recipe), f"network={file.name}", *extra,
                               f"hydra.run.dir={tmp_path / recipe}"], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=120)
        message = ("the PINN surrogate does not train on a network where the action range of Q of device 3 "
                   "(0 MW/MVAr), Q of device 4 (0 MW/MVAr) is a single value")
        assert proc.returncode != 0 and message in proc.stderr, proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr and not (tmp_path / recipe / "checkpoints").exists()


def _one_kind(kind: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """:func:`feeder` with one kind of controllable device: its storage unit alone, its PV unit alone, or that unit
    as a classical generator (type 1) alone."""
    net, load_p, gen_p_max = feeder()
    keep = {"storage": (3,), "renewable": (2,), "classical": (2,)}[kind]
    dev = [list(d) for d in net["device"] if d[2] in (0, -1, *keep)]
    if kind == "classical":
        dev = [d[:2] + [1] + d[3:] if d[2] == 2 else d for d in dev]
    return {**net, "device": dev}, load_p, gen_p_max[:, :0] if kind == "storage" else gen_p_max


@pytest.mark.parametrize("kind", ["storage", "renewable", "classical"])
def test_every_recipe_trains_on_a_network_with_one_kind_of_controllable_device(kind, tmp_path, caplog):
    """A user's network need not have every device kind. With only a storage unit, only a renewable or only a
    classical generator, one iteration of PPO, SAC and SHAC (tiny sizes, the per-network defaults of a user's file)
    collects and updates with finite losses, and the smoke PINN trains and steps as that network's surrogate env
    with finite rewards; its log says which module had no device to train (and extrapolates no time from it)."""
    import logging

    import torch

    from anm_torchrl.envs import SurrogateEnv
    from anm_torchrl.surrogates.pinn import train as tr
    from anm_torchrl.surrogates.pinn.load import load_pinn
    from anm_torchrl.training.algorithms import get_algorithm
    from anm_torchrl.training.network_defaults import compose_recipe_config
    from tests.test_recipes_ppo import TINY
    from tests.test_recipes_sac import TINY_SAC
    from tests.test_recipes_shac import TINY_SHAC

    file = N.save_network(tmp_path / f"{kind}_only.npz", *_one_kind(kind))
    for name, config, tiny in (("ppo", "config", TINY), ("sac", "sac", TINY_SAC), ("shac", "shac", TINY_SHAC)):
        cfg = compose_recipe_config([*tiny, f"network={file}"], config)[0]
        algo = get_algorithm(name)(cfg, device=torch.device("cpu"), seed=0, budget=64, reward_scale=1.0, resume=None)
        try:
            frames, metrics = algo.iterate(64)
        finally:
            algo.close()
        losses = {k: float(v) for k, v in metrics.items() if k.startswith("train/loss")}
        assert frames > 0 and losses and all(math.isfinite(v) for v in losses.values()), (name, metrics)
    sim = N.simulator(str(file))
    with caplog.at_level(logging.INFO, logger="anm_torchrl.surrogates.pinn.loop"):
        modules, report = tr.train_pinn(tr.preset("smoke"), sim)
    absent = "generator" if kind == "storage" else "storage"
    done = [r.getMessage() for r in caplog.records if " done: " in r.getMessage()]
    line = next(m for m in done if f" done: {absent}" in m)
    assert f"{absent}, no such device on this network, 0 steps" in line and "left" not in line, done
    path = tr.save_pinn(tmp_path / "pinn.safetensors", modules, tr.preset("smoke"), report, sim)
    td = SurrogateEnv(load_pinn(sim, path=path), num_envs=3, seed=0, sim=sim).rollout(4, break_when_any_done=False)
    assert td["next", "reward"].shape == (3, 4, 1) and torch.isfinite(td["next", "reward"]).all()


def test_an_unbounded_action_is_refused_for_training_and_by_the_random_baseline():
    """A valid network whose storage unit leaves PMAX / PMIN unset (gym-anm's ±inf; its corners P+ / P- bound it):
    the random baseline drew NaN actions and a trained policy's TanhNormal would too; both now refuse it by name."""
    import copy

    from anm_torchrl.baselines import RandomPolicy
    from anm_torchrl.networks import anm6_easy as a
    from anm_torchrl.networks.resolve import check_controllable
    from anm_torchrl.networks.user import checked_case

    net = copy.deepcopy(a.network())
    net["device"] = [list(d) for d in net["device"]]
    net["device"][6][4] = net["device"][6][5] = NAN  # PMAX, PMIN of the storage unit
    case = checked_case("unbounded", net, a.load_p(), a.gen_p_max())
    with pytest.raises(ValueError, match=r"'unbounded': the action range of P of device 6 \(\[-inf, inf\] MW/MVAr\) "
                                         "is unbounded"):
        check_controllable(case)
    with pytest.raises(ValueError, match=r"unbounded at P of device 6 \(\[-inf, inf\] MW/MVAr\): give those"):
        RandomPolicy(seed=0, sim=N.simulator(case))


def test_a_checkpoint_on_rewritten_profiles_is_evaluated_with_a_warning(tmp_path, caplog):
    """A network file rewritten with new profiles (same tables) was evaluated without a word: its figures differed
    from the run's summary.json (0.0013 against 0.0079 in a review). Other tables stay refused; the message no longer
    presumes a rewrite when another network was named."""
    import logging

    from anm_torchrl.grid.identity import profiles_key
    from anm_torchrl.networks.random import generate
    from anm_torchrl.training.checkpoint import check_network

    case = generate(11, n_bus=6, meshed=False)
    path = N.save_network(tmp_path / "f.npz", case.network, case.load_p, case.gen_p_max)
    sim = N.simulator(str(path))
    ckpt = {"network_key": network_key(sim), "profiles_key": profiles_key(sim), "config": {"network": str(path)}}
    with caplog.at_level(logging.WARNING):
        check_network(ckpt, sim)
    assert caplog.text == ""
    N.save_network(path, case.network, case.load_p * 1.5, case.gen_p_max * 0.5)
    with caplog.at_level(logging.WARNING):
        check_network(ckpt, N.simulator(str(path)))
    assert "trained on other load and generation profiles of this network" in caplog.text
    other = generate(12, n_bus=6, meshed=False)
    with pytest.raises(ValueError, match="trained on another network .*: another network, or that file with its "
                                         "tables or reward constants changed since"):
        check_network(ckpt, N.simulator(other.network, other.load_p, other.gen_p_max))
