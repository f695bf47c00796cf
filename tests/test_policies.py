"""The shipped policies (``pretrained:<name>``): every listed file is in the install, hash-checked, loads as an actor
and controls its network far better than doing nothing.

A listed policy whose file was never committed (``*.pt`` is git-ignored outside this folder) fails here on a clean
clone, which is what CI runs on.
"""

from __future__ import annotations

import pytest
import torch

from anm_torchrl.policies import PREFIX, SUMS, available_pretrained, pretrained_path, resolve
from anm_torchrl.training.checkpoint import load_actor, load_checkpoint


def test_every_listed_policy_is_shipped_and_matches_its_hash():
    names = available_pretrained()
    assert "anm6_easy" in names, SUMS.read_text()
    for name in names:
        path = pretrained_path(name)  # raises on a missing file or another hash
        assert path.is_file() and resolve(PREFIX + name) == path


def test_every_shipped_policy_names_its_network_as_it_is_now():
    """Each checkpoint records its network's key (tables and reward constants), so evaluate.py refuses it on another
    version of the network; the key is the registered network's of today's code (the policies re-scored their
    records to the last digit before their keys were written, policies/README.md)."""
    from anm_torchrl.grid.identity import network_key
    from anm_torchrl.networks import simulator

    for name in available_pretrained():
        ckpt = load_checkpoint(pretrained_path(name))
        assert ckpt["config"]["network"] == name
        assert ckpt.get("network_key") == network_key(simulator(name)), name


def test_publish_refuses_a_checkpoint_without_its_network_key(tmp_path, monkeypatch):
    import anm_torchrl.policies as policies
    from anm_torchrl.training.checkpoint import save_checkpoint

    ckpt = load_checkpoint(pretrained_path("case33bw"))
    old = {k: v for k, v in ckpt.items() if k not in ("kind", "format_version", "sha256", "network_key")}
    save_checkpoint(tmp_path / "old.pt", old)
    monkeypatch.setattr(policies, "FOLDER", tmp_path / "shipped")
    monkeypatch.setattr(policies, "SUMS", tmp_path / "shipped" / "SHA256SUMS")
    with pytest.raises(ValueError, match="records no network key"):
        policies.publish(tmp_path / "old.pt", "case33bw")
    assert not (tmp_path / "shipped").exists()


def test_unknown_or_corrupted_policies_fail_clearly(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="no pretrained policy 'nope'; shipped: .*anm6_easy"):
        pretrained_path("nope")
    import anm_torchrl.policies as policies

    fake = tmp_path / "anm6_easy.pt"
    fake.write_bytes(b"not the published file")
    monkeypatch.setattr(policies, "FOLDER", tmp_path)
    with pytest.raises(ValueError, match="is corrupted: sha256"):
        pretrained_path("anm6_easy")


def test_anm6_policy_beats_doing_nothing_on_a_test_state():
    """The ANM6-Easy policy (SHAC through the exact simulator) on test state 0 of the gap table, 500 steps, must keep
    its loss under half of do-nothing's there: do-nothing loses 66x the optimum's return over the 8 test states and
    the published policy 1.08x (policies README), so a broken or random actor fails while noise in the policy's
    training does not."""
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.envs import ANM6Env
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy

    ckpt = load_checkpoint(pretrained_path("anm6_easy"))
    assert ckpt["algorithm"] == "shac" and ckpt["config"].get("network", "anm6_easy") == "anm6_easy"
    actor = load_actor(ckpt)
    state = draw_initial_states(8, 0)[:1]
    policy = evaluate_policy(actor, state, max_steps=500, env=ANM6Env(1, seed=0))
    idle = evaluate_policy(make_baseline("do_nothing"), state, max_steps=500, env=ANM6Env(1, seed=0))
    assert not bool(policy.terminated.any())
    assert torch.isfinite(policy.discounted_returns).all()
    assert float(policy.discounted_returns) > 0.5 * float(idle.discounted_returns), (policy.discounted_returns,
                                                                                     idle.discounted_returns)


FEEDERS = [name for name in available_pretrained() if name != "anm6_easy"]


@pytest.mark.parametrize("name", FEEDERS)
def test_feeder_policy_beats_doing_nothing_on_a_test_state(name):
    """Each shipped feeder policy (SHAC, README of the policies folder: 96–99 % of the optimum's gain over do-nothing
    on its 4 test states) on its network's test state 0 over 300 steps (78 % of an episode's discounted weight).
    The optimum's whole gain is 9 % of do-nothing's loss on the SimBench feeder (no storage: -0.661 against -0.731),
    more than do-nothing's loss on the feeders with storage; beating do-nothing by 4 % of its return is half the
    smallest of these, a bar that a random, untrained or wrong-network actor does not clear."""
    from anm_torchrl.baselines import make_baseline
    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.factory import make_true_env

    ckpt = load_checkpoint(pretrained_path(name))
    assert ckpt["config"]["network"] == name
    actor = load_actor(ckpt, env=make_true_env(1, network=name))
    env = make_true_env(1, network=name, seed=0)
    state = draw_initial_states(4, 0, env.sim, env.init)[:1]
    policy = evaluate_policy(actor, state, max_steps=300, env=env)
    idle_env = make_true_env(1, network=name, seed=0)
    idle = evaluate_policy(make_baseline("do_nothing", idle_env.sim), state, max_steps=300, env=idle_env)
    assert not bool(policy.terminated.any())
    p, d = float(policy.discounted_returns), float(idle.discounted_returns)
    assert p - d > 0.04 * abs(d), (p, d)
