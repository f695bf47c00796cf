"""Issue 25: failures that were silent, cryptic or left debris behind. Each test was seen failing before its fix;
its docstring names the bug of the issue it covers."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "recipes" / "conf"
torch.set_num_threads(1)


def make_dataset_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="make_dataset", overrides=list(overrides))


# ------------------------------------------------------------------------------- bug 5: make_dataset options
@pytest.mark.parametrize("override, message", [
    ("generative.chunk=0", "generative.chunk must be an integer >= 1, got 0"),
    ("agent.num_envs=0", "agent.num_envs must be an integer >= 1, got 0"),
    ("agent.max_episode_steps=0", "agent.max_episode_steps must be an integer >= 1, got 0"),
    ("fractions=[0.5,0.5,0.5]", "fractions must be three positive numbers .* summing to 1"),
    # a review's finding: an empty validation split kept a DNN's first epoch, its metrics null
    ("fractions=[0.9,0.0,0.1]", r"fractions must be three positive numbers .* \(each split needs rows\)"),
    ("agent.num_envs=3 size=4", r"size=4 rows over agent.num_envs=3 envs fill 2 envs \(2 steps each\)"),
    ("size=0", "size must be an integer >= 1, got 0"),
    ("threads=0", "threads must be an integer >= 1, got 0"),
])
def test_make_dataset_options_checked_up_front(override, message, tmp_path, monkeypatch):
    """Bug 5: make_dataset options are range-checked before any work, one line naming the key (before: "negative
    dimension -1", ZeroDivisionError, silent renormalisation, 100,000 one-step episodes)."""
    sys.path.insert(0, str(ROOT / "recipes"))
    try:
        import make_dataset as recipe
    finally:
        sys.path.remove(str(ROOT / "recipes"))
    dataset = "agent" if override.startswith("agent.") else "generative"
    cfg = make_dataset_config(*override.split(), f"dataset={dataset}", f"out={tmp_path / 'ds'}", "progress=false")
    import anm_torchrl.networks as networks

    monkeypatch.setattr(networks, "simulator", lambda *a, **k: pytest.fail("heavy work started before the check"))
    with pytest.raises(ValueError, match=message):
        recipe.run(cfg)
    assert not (tmp_path / "ds").exists()


def test_make_dataset_default_config_passes():
    """Bug 5: the shipped defaults pass the new check, for both dataset kinds."""
    from anm_torchrl.training.config_checks import check_make_dataset_config

    check_make_dataset_config(make_dataset_config())
    check_make_dataset_config(make_dataset_config("dataset=agent"))


@pytest.mark.parametrize("kind, options, key", [
    ("generative", {"chunk": 0}, "chunk"), ("agent", {"num_envs": 0}, "num_envs"),
    ("agent", {"max_episode_steps": 0}, "max_episode_steps")])
def test_dataset_generators_refuse_bad_options(kind, options, key):
    """Bug 5: the library generators refuse the same values (callers that skip the recipe)."""
    from anm_torchrl.data import generate
    from anm_torchrl.networks import simulator

    with pytest.raises(ValueError, match=f"{key} must be an integer >= 1, got 0"):
        generate(kind, 10, 0, sim=simulator("anm6_easy"), **options)


# ------------------------------------------------------------------------------ bugs 1, 2: full disk, locks
def _small_dataset():
    from anm_torchrl.data import generate
    from anm_torchrl.networks import simulator

    return generate("generative", 30, 0, sim=simulator("anm6_easy"))


def _enospc(*args, **kwargs):
    import errno

    raise OSError(errno.ENOSPC, "No space left on device")


def _siblings(path: Path) -> list[str]:
    return sorted(p.name for p in path.parent.iterdir() if p.name != path.name)


@pytest.mark.parametrize("where", ["fallocate", "free_space", "metadata"])
def test_full_disk_during_save_leaves_nothing_behind(where, tmp_path, monkeypatch):
    """Bug 1: a full disk while a dataset is written raises a clear ENOSPC error naming the path and the space
    needed/free; no temporary folder or lock stays behind and the previous dataset is intact (before: SIGBUS in
    the memory-mapped writes, rc 135, lock and temporary folder left holding the space)."""
    import errno
    import os
    import shutil

    from anm_torchrl.artifacts import DiskFullError
    from anm_torchrl.data import load_dataset, save_dataset

    td, meta = _small_dataset()
    path = tmp_path / "ds"
    save_dataset(td, path, meta)
    before = load_dataset(path)[1]["checksum"]
    if where == "fallocate":
        monkeypatch.setattr(os, "posix_fallocate", _enospc)
    elif where == "free_space":
        usage = shutil.disk_usage(tmp_path)
        monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=100))
    else:
        monkeypatch.setattr(Path, "write_text", _enospc)
    with pytest.raises(DiskFullError, match=f"no space left .* to write {path}.*free; nothing was written") as err:
        save_dataset(td, path, meta, overwrite=True)
    assert err.value.errno == errno.ENOSPC
    if where != "metadata":
        assert "needs about" in str(err.value)
    monkeypatch.undo()
    assert _siblings(path) == []  # no .ds.tmp-*, no .ds.lock
    assert load_dataset(path)[1]["checksum"] == before


def test_full_disk_in_make_dataset_releases_lock(tmp_path, monkeypatch):
    """Bug 1: make_dataset (lock held around generation and save) leaves no lock and no folder on a full disk."""
    import os

    from anm_torchrl.artifacts import DiskFullError
    from anm_torchrl.data import make_dataset
    from anm_torchrl.networks import simulator

    path = tmp_path / "ds"
    monkeypatch.setattr(os, "posix_fallocate", _enospc)
    with pytest.raises(DiskFullError, match=str(path)):
        make_dataset("generative", 20, 0, path=path, sim=simulator("anm6_easy"))
    assert list(tmp_path.iterdir()) == []


def test_full_disk_in_atomic_write_is_disk_full_error(tmp_path, monkeypatch):
    """Bug 1: every atomic save (here a safetensors file) turns ENOSPC into DiskFullError naming the path, keeps the
    previous file and leaves no temporary."""
    import os

    from anm_torchrl.artifacts import DiskFullError, load_tensors, save_tensors

    path = tmp_path / "w.safetensors"
    save_tensors(path, {"w": torch.ones(3)}, {}, kind="test")
    monkeypatch.setattr(os, "fsync", _enospc)
    with pytest.raises(DiskFullError, match=f"to write {path}"):
        save_tensors(path, {"w": torch.zeros(3)}, {}, kind="test")
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["w.safetensors"]
    assert load_tensors(path, kind="test")[0]["w"].tolist() == [1.0, 1.0, 1.0]


def test_failed_lock_write_leaves_no_lock(tmp_path, monkeypatch):
    """Bug 2: a lock whose write fails (full disk) leaves no empty lock behind, and the path can be written once
    space is back (before: an empty lock file, then "host None, pid None" on every later write)."""
    import os

    from anm_torchrl.artifacts import DiskFullError, exclusive_lock

    path = tmp_path / "art"
    real_write = os.write
    monkeypatch.setattr(os, "write", _enospc)
    with pytest.raises(DiskFullError, match="lock"):
        with exclusive_lock(path):
            pass
    monkeypatch.setattr(os, "write", real_write)
    assert list(tmp_path.iterdir()) == []
    with exclusive_lock(path) as lock:
        assert lock.is_file()
    assert list(tmp_path.iterdir()) == []


def test_empty_lock_is_stale_once_old(tmp_path):
    """Bug 2: an empty (or unreadable) lock left by a failed write of an older version is broken once older than
    STALE_EMPTY_LOCK_S, and reported clearly while younger (before: "host None, pid None" forever)."""
    import os
    import time

    from anm_torchrl.artifacts import STALE_EMPTY_LOCK_S, LockedError, exclusive_lock

    path = tmp_path / "art"
    lock = tmp_path / ".art.lock"
    lock.write_bytes(b"")
    with pytest.raises(LockedError, match="empty or unreadable"):
        with exclusive_lock(path):
            pass
    old = time.time() - STALE_EMPTY_LOCK_S - 5
    os.utime(lock, (old, old))
    with exclusive_lock(path):
        assert lock.read_text().startswith("{")
    assert not lock.exists()


def test_live_lock_still_excludes(tmp_path):
    """Bug 2: the atomic lock still refuses a second writer, naming the holder."""
    from anm_torchrl.artifacts import LockedError, exclusive_lock

    with exclusive_lock(tmp_path / "art"):
        with pytest.raises(LockedError, match="being written by another process .* pid"):
            with exclusive_lock(tmp_path / "art"):
                pass


# ----------------------------------------------------------------------------------------- bug 7: action dtypes
@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.int64])
def test_real_action_dtypes_are_cast(backend, dtype):
    """Bug 7: a float16 (bfloat16, int) action is cast exactly to float64 and steps as the float64 action does
    (before: NotImplementedError float16 inside numba, on both backends)."""
    from anm_torchrl.envs import ANM6Env

    env = ANM6Env(num_envs=2, seed=0, backend=backend)
    td = env.reset()
    a = torch.zeros(2, env.action_spec.shape[-1])
    want = env.step(td.clone().set("action", a.to(torch.float64)))["next", "state"]
    got = env.step(td.clone().set("action", a.to(dtype)))["next", "state"]
    torch.testing.assert_close(got, want, rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [torch.bool, torch.complex64])
def test_non_real_action_dtypes_are_refused(dtype):
    """Bug 7: a bool or complex action is refused naming its dtype (before: bool accepted as 0/1 MW)."""
    from anm_torchrl.envs import ANM6Env

    env = ANM6Env(num_envs=2, seed=0)
    td = env.reset()
    with pytest.raises(TypeError, match=f"action dtype {dtype} is not supported"):
        env.step(td.set("action", torch.zeros(2, env.action_spec.shape[-1], dtype=dtype)))


def test_gym_adapter_action_dtypes():
    """Bug 7: the gymnasium adapters cast float16/int actions and refuse bool/complex/object ones, naming the
    dtype (before: bool silently 0/1 MW)."""
    import numpy as np

    from anm_torchrl.gym.env import ANMGymEnv

    env = ANMGymEnv()
    env.reset(seed=0)
    n = env.action_space.shape[0]
    env.step(np.zeros(n, dtype=np.float16))
    env.step(np.zeros(n, dtype=np.int32))
    for dtype in (np.bool_, np.complex128, object):
        with pytest.raises(TypeError, match="action dtype .* is not supported"):
            env.step(np.zeros(n, dtype=dtype))


# ------------------------------------------------------------------------- bugs 4, 6: network validation
_ = float("nan")
_DEVICES_1BUS = [[0, 0, 0, _, 200, -200, 200, -200, _, _, _, _, _, _, _],
                 [1, 0, -1, 0.2, 0, -10, _, _, _, _, _, _, _, _, _]]


def _anm6(**changes):
    from anm_torchrl.networks import anm6_easy as a

    net = {"baseMVA": a.BASE_MVA, "bus": a.BUSES, "branch": a.BRANCHES, "device": a.DEVICES}
    return {**net, **changes}


def test_disconnected_network_names_the_islands():
    """Bug 4: a network whose buses are not all connected to the slack is refused at validation, naming them
    (before: accepted, then "2 sampled states did not converge after 100 attempts" at reset)."""
    from anm_torchrl.networks.validation import validate_network

    branches = [br for br in _anm6()["branch"] if tuple(br[:2]) != (2, 4)]  # bus 4 cut off
    with pytest.raises(ValueError, match=r"disconnected: bus\(es\) \[4\] are not connected to the slack bus 0"):
        validate_network(_anm6(branch=branches))
    branches = [br for br in _anm6()["branch"] if tuple(br[:2]) != (1, 2)]  # buses 2, 4, 5 cut off
    with pytest.raises(ValueError, match=r"bus\(es\) \[2, 4, 5\]"):
        validate_network(_anm6(branch=branches))
    validate_network(_anm6())


def test_disconnected_network_fails_at_build_not_reset():
    """Bug 4: building a simulator (hence an env) of a disconnected network fails at once, naming the islands."""
    import numpy as np

    from anm_torchrl.networks import simulator

    branches = [br for br in _anm6()["branch"] if tuple(br[:2]) != (2, 5)]
    with pytest.raises(ValueError, match=r"bus\(es\) \[5\] are not connected"):
        simulator(_anm6(branch=branches), np.full((4, 3), -1.0), np.full((4, 2), 1.0))


@pytest.mark.parametrize("branch", [[], "array"])
def test_empty_branch_table_is_a_table(branch):
    """Bug 6: an empty table is a valid (0, ncols) array, not "ragged rows"; a one-bus network is then refused
    deliberately, saying why (before: "must have 8 columns ..., got ragged rows")."""
    import numpy as np

    from anm_torchrl.networks.validation import _table, validate_network

    branch = np.zeros((0, 8)) if branch == "array" else branch
    assert _table({"branch": branch}, "branch", tuple("abcdefgh")).shape == (0, 8)
    net = {"baseMVA": 100.0, "bus": [[0, 0, 33, 1.0, 1.0]], "branch": branch, "device": _DEVICES_1BUS}
    with pytest.raises(ValueError, match="one-bus network .* is not supported, because the power flow"):
        validate_network(net)
    with pytest.raises(ValueError, match="network table 'device' is empty"):
        validate_network(_anm6(device=[]))


# ------------------------------------------------------------------------------ bug 3: hook outputs checked
def _anm6_sim(**kwargs):
    from anm_torchrl.networks import simulator

    return simulator("anm6_easy", **kwargs)


def _valid_init(sim):
    from anm_torchrl.grid import reset as grid_reset

    def init(n, generator):
        return grid_reset.random_state(sim, n, generator)[0]

    return init


@pytest.mark.parametrize("bad, message", [("soc", r"SoC \(MWh\) must lie in"), ("nan", "non-finite state")])
def test_init_sampler_output_is_validated(bad, message):
    """Bug 3: an init= sampler's states go through the state validator, and the error names the sampler
    (before: reset() returned SoC 500 MWh > SOC_MAX; a NaN was reported as "did not converge")."""
    from anm_torchrl.envs import ANMEnv

    sim = _anm6_sim()
    good = _valid_init(sim)
    soc_col = sim.state_slices()["des_soc"].start

    def broken_init(n, generator):
        s = good(n, generator).clone()
        s[:, soc_col] = 500.0 if bad == "soc" else float("nan")
        return s

    env = ANMEnv(sim=sim, num_envs=2, seed=0, init=broken_init)
    with pytest.raises(ValueError, match=f"init= reset sampler 'broken_init' returned an invalid state: {message}"):
        env.reset()
    ANMEnv(sim=sim, num_envs=2, seed=0, init=good).reset()


def test_next_vars_hook_nan_is_an_error():
    """Bug 3: a next_vars hook returning NaN raises naming the hook (before: every step terminal at -20,000,
    no error)."""
    import numpy as np

    from anm_torchrl.envs import ANMEnv
    from anm_torchrl.networks import anm6_easy as a

    sim = _anm6_sim()
    n_load, n_gen = sim.n_load, sim.n_gen

    def nan_vars(state):
        n = state.shape[0]
        return (torch.full((n, n_load), float("nan"), dtype=state.dtype), torch.zeros(n, n_gen, dtype=state.dtype),
                torch.zeros(n, 1, dtype=state.dtype))

    net = {"baseMVA": a.BASE_MVA, "bus": a.BUSES, "branch": a.BRANCHES, "device": a.DEVICES}
    load_p = np.full((4, n_load), -1.0)
    gen_p_max = np.full((4, n_gen), 1.0)
    env = ANMEnv(net, load_p, gen_p_max, num_envs=2, seed=0, next_vars=nan_vars)
    td = env.reset()
    with pytest.raises(ValueError, match="next_vars hook 'nan_vars' returned non-finite load P at"):
        env.step(td.set("action", torch.zeros(2, env.action_spec.shape[-1])))


def test_clipped_profiles_are_reported_once(caplog, monkeypatch):
    """Weak point: profiles with positive loads or potentials beyond PMAX are clipped as gym-anm does, and now said
    so once per case at WARNING, naming device, bound and extreme (before: silently); so is a hook's output."""
    import logging

    import numpy as np

    import anm_torchrl.grid.simulator as simulator_module
    from anm_torchrl.envs import ANMEnv
    from anm_torchrl.networks import anm6_easy as a

    monkeypatch.setattr(simulator_module, "_REPORTED", set())
    net = {"baseMVA": a.BASE_MVA, "bus": a.BUSES, "branch": a.BRANCHES, "device": a.DEVICES}
    sim = _anm6_sim()
    load_p = np.full((4, sim.n_load), -1.0)
    gen_p_max = np.full((4, sim.n_gen), 1.0)
    load_p[2, 0] = 5.0  # a load that produces: above its PMAX of 0 MW
    gen_p_max[1, 1] = 1e6  # far above the generator's PMAX
    caplog.clear()  # ANM6-Easy's own wind profile passes its PMAX (gym-anm's data): reported by _anm6_sim
    with caplog.at_level(logging.WARNING, logger="anm_torchrl.grid.simulator"):
        ANMEnv(net, load_p, gen_p_max, num_envs=2, seed=0)
        ANMEnv(net, load_p, gen_p_max, num_envs=2, seed=1)  # the same case: not repeated
    records = [r.getMessage() for r in caplog.records if r.name == "anm_torchrl.grid.simulator"]
    assert len(records) == 1, records
    assert "load P of device 1 above PMAX (0 MW) at 1 entries (extreme 5 MW)" in records[0]
    assert "potential of device" in records[0] and "extreme 1e+06 MW" in records[0]

    def hot(state):
        n = state.shape[0]
        return (torch.full((n, sim.n_load), 2.0, dtype=state.dtype), torch.zeros(n, sim.n_gen, dtype=state.dtype),
                torch.zeros(n, 1, dtype=state.dtype))

    env = ANMEnv(net, np.full((4, sim.n_load), -1.0), np.full((4, sim.n_gen), 1.0), num_envs=2, seed=0, next_vars=hot)
    td = env.reset()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="anm_torchrl.grid.simulator"):
        for _ in range(2):
            td = env.step(td.set("action", torch.zeros(2, env.action_spec.shape[-1])))["next"]
    records = [r.getMessage() for r in caplog.records if r.name == "anm_torchrl.grid.simulator"]
    assert len(records) == 1 and records[0].startswith("the next_vars hook 'hot' hold values"), records


def test_clipping_line_names_its_network_and_no_other_network_is_reported(caplog, monkeypatch):
    """Bug found on a user's file (main job on a 30-bus random network): the run's log carried "the profiles hold
    values outside the devices' limits ... device 2 above PMAX (30 MW)", ANM6-Easy's wind, because asking whether a
    network is ANM6-Easy built ANM6-Easy's simulator; the line also did not say whose profiles it meant."""
    import logging

    import anm_torchrl.grid.simulator as simulator_module
    from anm_torchrl.networks import simulator
    from anm_torchrl.networks.random import generate
    from anm_torchrl.networks.resolve import _anm6_key, is_anm6

    monkeypatch.setattr(simulator_module, "_REPORTED", set())
    _anm6_key.cache_clear()
    # a 6-bus network (ANM6-Easy's bus count) still built ANM6-Easy's simulator, and its line, to compare keys
    for case in (generate(7003, n_bus=9), generate(4242, n_bus=6, meshed=False)):
        with caplog.at_level(logging.INFO, logger="anm_torchrl.grid.simulator"):
            assert not is_anm6(simulator(case.network, case.load_p, case.gen_p_max))
        assert not [r for r in caplog.records if "anm6_easy" in r.getMessage() or "PMAX (30 MW)" in r.getMessage()]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="anm_torchrl.grid.simulator"):
        assert is_anm6(simulator("anm6_easy"))
    assert [r.getMessage() for r in caplog.records][0].startswith("the profiles of network 'anm6_easy' hold values")


def test_reset_mask_must_be_bool():
    """Extra: a float '_reset' mask raises a clear error naming dtype and shape (before: a raw TypeError)."""
    from tensordict import TensorDict

    from anm_torchrl.envs import ANMEnv

    env = ANMEnv(sim=_anm6_sim(), num_envs=2, seed=0)
    env.reset()
    with pytest.raises(ValueError, match="'_reset' must be a bool mask of 2 entries .* got torch.float32"):
        env._reset(TensorDict({"_reset": torch.ones(2, 1)}, [2]))


@pytest.mark.parametrize("kwargs, message", [
    ({"num_envs": 2.7}, "num_envs must be an integer >= 1, got 2.7"),
    ({"num_envs": 0}, "num_envs must be an integer >= 1, got 0"),
    ({"seed": "abc"}, "seed must be an integer or None, got 'abc'"),
    ({"max_steps": 0}, "max_steps must be an integer >= 1 or None, got 0")])
def test_make_env_arguments_checked(kwargs, message):
    """Extra: make_env refuses a fractional num_envs (before: truncated silently) and a non-integer seed (before:
    a raw error from torch) with a line naming the argument."""
    from anm_torchrl.training.factory import make_env

    with pytest.raises(ValueError, match=message):
        make_env(**kwargs)


@pytest.mark.parametrize("fractions", [(0.5, 0.5, 0.5), (0.8, 0.2), (1.2, -0.1, -0.1), (True, 0, 0), 5,
                                       (0.9, 0.0, 0.1), (1.0, 0.0, 0.0)])
def test_split_fractions_are_never_renormalised(fractions):
    """Bug 5: the library's split refuses fractions that do not sum to 1 (before: [0.5, 0.5, 0.5] silently
    became thirds), or that leave a split empty; the recipe's check is this same function."""
    from anm_torchrl.data.storage import split_codes

    with pytest.raises(ValueError, match="fractions must be three positive numbers .* summing to 1"):
        split_codes(10, fractions)
    assert split_codes(10, [0.8, 0.1, 0.1]).bincount().tolist() == [8, 1, 1]


@pytest.mark.parametrize("kwargs, message", [
    ({"num_envs": 2.7}, "num_envs must be an integer >= 1, got 2.7"),
    ({"num_envs": 0}, "num_envs must be an integer >= 1, got 0"),
    ({"seed": "abc"}, "seed must be an integer, got 'abc'")])
def test_env_constructor_arguments_checked(kwargs, message):
    """Extra: the env itself (not only make_env) refuses a fractional num_envs and a non-integer seed."""
    from anm_torchrl.envs import ANM6Env

    with pytest.raises(ValueError, match=message):
        ANM6Env(**kwargs)


def _rollout_states_pass_the_validator(env, steps: int, seed: int) -> int:
    """Step ``env`` with uniform random actions for ``steps`` steps, auto-resetting terminated grids (partial
    resets); every reset state and every non-terminal next state must pass the simulator's state validator.
    Returns the number of partial resets seen."""
    from tensordict import TensorDict

    sim = env.sim
    gen = torch.Generator().manual_seed(seed)
    lo, hi = (b.to(torch.float32) for b in sim.action_bounds())
    td = env.reset()
    sim.check_state(td["state"])
    resets = 0
    for _ in range(steps):
        n = env.batch_size[0]
        td.set("action", lo + torch.rand(n, lo.numel(), generator=gen) * (hi - lo))
        out, td = env.step_and_maybe_reset(td)
        nxt, term = out["next", "state"], out["next", "terminated"].reshape(-1)
        if (~term).any():
            sim.check_state(nxt[~term])
        resets += int(term.sum())
        sim.check_state(td["state"])  # the states the next step starts from, reset rows included
    return resets


@pytest.mark.parametrize("network", ["anm6_easy", "case33bw", "cigre_mv", "random:3", "random:9"])
def test_long_rollout_states_pass_the_validator(network):
    """Issue 25 (tests section): every reset and step output of a long random-action rollout with partial resets
    passes the one state validator, on the registered networks and on two random ones (one meshed); SimBench's
    115 buses are covered by the same code path at a larger size and left to the slow parity tests."""
    from anm_torchrl.networks import random as rnd
    from anm_torchrl.training.factory import make_true_env

    if network.startswith("random:"):
        case = rnd.generate(int(network.split(":")[1]), n_bus=12)
        env = make_true_env(32, seed=0, network=case.network, load_p=case.load_p, gen_p_max=case.gen_p_max)
    else:
        env = make_true_env(32, seed=0, network=network)
    _rollout_states_pass_the_validator(env, 300, seed=1)


def test_full_disk_while_saving_a_checkpoint_keeps_the_previous_one(tmp_path, monkeypatch):
    """Weak point: a full disk while PPO writes a checkpoint raised torch's raw ``RuntimeError: [enforce fail at
    inline_container.cc]``; now it is a DiskFullError naming the file and saying the previous one is intact, and the
    previous checkpoint still loads."""
    import os

    from anm_torchrl.artifacts import DiskFullError
    from anm_torchrl.training.checkpoint import save_checkpoint

    import io

    path = tmp_path / "last.pt"
    targets, real_save = [], torch.save
    monkeypatch.setattr(torch, "save", lambda obj, f, *a, **k: (targets.append(type(f)), real_save(obj, f, *a, **k)))
    save_checkpoint(path, {"update": 1})
    assert targets == [io.BytesIO]  # torch's own file writer never meets the disk: its errors are not ENOSPC
    monkeypatch.setattr(os, "fsync", _enospc)
    with pytest.raises(DiskFullError, match=f"to write {path}.*previous version is intact"):
        save_checkpoint(path, {"update": 2})
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]
    assert torch.load(path, weights_only=True)["update"] == 1


def test_ill_conditioned_branch_is_refused():
    """Weak point: a branch with x = 1e-12 p.u. was accepted and the two backends disagreed on terminations; it is
    refused now, naming the branch and what to do, while 1e-6 p.u. (where they agree to 4e-8 MW) is accepted."""
    import copy

    import numpy as np

    from anm_torchrl.networks import get_network, simulator

    case = get_network("anm6_easy")
    for x, ok in ((1e-12, False), (1e-6, True)):
        net = copy.deepcopy(case.network)
        br = np.array(net["branch"], dtype=float)
        br[2, 2], br[2, 3] = 0.0, x
        net["branch"] = br
        if ok:
            simulator(net, case.load_p, case.gen_p_max)
        else:
            with pytest.raises(ValueError, match=r"branch \(.*BR_X.*below 1e-06 p.u.*merge the two buses"):
                simulator(net, case.load_p, case.gen_p_max)


def test_anm6_initial_distribution_is_refused_on_other_networks():
    """Smaller weak point: ``init="gym_anm"`` was accepted on case33bw (ANM6-Easy's device indices and quirks applied
    to another network); it is refused with what to use instead, and still accepted on ANM6-Easy."""
    from anm_torchrl.training.factory import make_true_env

    for init in ("gym_anm", "intended"):
        with pytest.raises(ValueError, match=f"init='{init}' is ANM6-Easy's initial distribution.*init='uniform'"):
            make_true_env(2, seed=0, network="case33bw", init=init)
        assert make_true_env(2, seed=0, init=init).reset()["state"].shape == (2, 18)


def test_set_state_honours_a_partial_reset_mask():
    """Smaller weak point: ``reset(set_state=True)`` with a ``_reset`` mask checked and solved every row, so a
    row not being reset that no transition could start from made it raise; only the masked rows are set now, and the others
    keep their values (TorchRL's partial-reset rule)."""
    from tensordict import TensorDict

    from anm_torchrl.envs import ANM6Env

    env = ANM6Env(2, seed=0)
    state = env.reset()["state"].clone()
    given = state.clone()
    given[0, 0] = float("nan")  # a row not valid to start from, and not being reset
    out = env.reset(TensorDict({"state": given, "_reset": torch.tensor([[False], [True]])}, [2]), set_state=True)
    torch.testing.assert_close(out["state"][1], given[1])
    assert not bool(out["terminated"][1])


def test_every_split_holds_a_unit_and_the_generative_counts_are_the_points_used():
    """A review's findings: rounding could leave the training split empty (a tiny train fraction), and the
    generative dataset's metadata counted the whole Sobol chunk drawn (8,192 points and their invalid states for
    2,000 rows) instead of the points the rows came from; a dataset of valid points only has
    points_drawn = size + invalid_states_skipped."""
    from anm_torchrl.data.generative import generate_generative
    from anm_torchrl.data.storage import split_codes
    from anm_torchrl.networks import simulator

    codes = split_codes(4, (0.0002, 0.4999, 0.4999), torch.Generator().manual_seed(0))
    assert sorted(codes.tolist()) == [0, 1, 2, 2] or sorted(codes.tolist()) == [0, 1, 1, 2]
    _, meta = generate_generative(200, 0, sim=simulator("anm6_easy"), chunk=4096, progress=False)
    gen = meta["generator"]
    assert gen["points_drawn"] == 200 + gen["invalid_states_skipped"] < 4096
