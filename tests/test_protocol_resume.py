"""The protocol's checkpoints across a crash and a resume (in-process, tiny PPO runs): last.pt is written when due
even while a validation pass runs in the second process, and holds that pass so a resumed run takes it; a resumed run
keeps a best.pt newer than last.pt's record; an early-stopped run resumed with the same patience trains nothing; a
resumed run that evaluates nothing reports the last evaluation; best.pt's curve ends at its own point. Each test
failed on the protocol before these fixes."""

from __future__ import annotations

import json

import pytest
import torch

from anm_torchrl.training import validation as validation_module
from anm_torchrl.training.algorithms import get_algorithm
from anm_torchrl.training.checkpoint import load_checkpoint, save_checkpoint
from anm_torchrl.training.protocol import train
from tests.test_recipes_ppo import TINY

BASE = [*TINY, "logger.backend=null", "eval.patience=null"]


def _cfg(*overrides):
    from recipe_utils import compose

    return compose("config", [*BASE, *overrides])


class Crash(RuntimeError):
    pass


@pytest.fixture
def crash_at(monkeypatch):
    """``crash_at(n)``: PPO's ``iterate`` raises :class:`Crash` on its n-th call (an env error, out of memory)."""
    cls = get_algorithm("ppo")
    original = cls.iterate

    def arm(n: int):
        calls = {"n": 0}

        def iterate(self, remaining):
            calls["n"] += 1
            if calls["n"] == n:
                raise Crash(f"crash in iteration {n}")
            return original(self, remaining)

        monkeypatch.setattr(cls, "iterate", iterate)
    return arm


@pytest.fixture
def slow_background(monkeypatch):
    """A background validation pass that is never done before the protocol waits for it (a pass longer than the
    updates between two passes, as the main job's 3,000-step passes are): results come only when waited for."""
    original = validation_module.BackgroundValidation.results

    def results(self, wait: bool = False):
        return original(self, wait=True) if wait else []

    monkeypatch.setattr(validation_module.BackgroundValidation, "results", results)


def test_last_pt_is_written_while_a_background_pass_runs_and_a_resume_takes_that_pass(tmp_path, crash_at,
                                                                                      slow_background):
    """Bug: last.pt was saved only at an update with no pass pending, so with passes in the second process it was
    never saved before the end (a crash lost the whole run). It is now saved when due, with the pending pass's policy
    in it; the resumed run validates that policy first, so its curve has every update's point."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    crash_at(6)
    with pytest.raises(Crash):
        train(_cfg("collector.total_frames=256", "eval.background=true"), run)
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    assert last["update"] == 5 and last["frames"] == 160
    assert [p["update"] for p in last["curve"]] == [1, 2, 3, 4]  # update 5's pass was still running
    assert [tag["update"] for tag in last["pending"]] == [5]
    resumed = train(_cfg("collector.total_frames=256", f"checkpoint.resume={run / 'checkpoints' / 'last.pt'}"),
                    tmp_path / "resumed")
    assert [p["update"] for p in resumed["curve"]] == list(range(1, 9))
    assert resumed["frames"] == 256 and resumed["updates"] == 8


def test_a_resume_keeps_a_best_pt_newer_than_last_pt(tmp_path):
    """Bug: a resumed run took its best-so-far from last.pt; best.pt (written at every new best) can be newer and
    better after a crash between the two saves, and the first resumed pass beating last.pt's stale value overwrote
    it. A stale last.pt is made here from a finished run (its best set to its worst point)."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    first = train(_cfg("collector.total_frames=128"), run)
    best_pt = load_checkpoint(run / "checkpoints" / "best.pt")
    worst = min(first["curve"], key=lambda p: p["validation"])
    assert worst["validation"] < best_pt["best_eval"]["discounted_return"]
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    stale = {"discounted_return": worst["validation"], "frames": worst["frames"], "update": worst["update"]}
    save_checkpoint(run / "checkpoints" / "last.pt", {k: v for k, v in {**last, "best_eval": stale}.items()
                                                        if k not in ("kind", "format_version", "sha256")})
    resumed = train(_cfg("collector.total_frames=256", f"checkpoint.resume={run / 'checkpoints' / 'last.pt'}"),
                    tmp_path / "resumed")
    kept = load_checkpoint(tmp_path / "resumed" / "checkpoints" / "best.pt")["best_eval"]
    assert kept["discounted_return"] >= best_pt["best_eval"]["discounted_return"]
    assert resumed["best_eval"]["discounted_return"] == kept["discounted_return"]
    later = [p["validation"] for p in resumed["curve"] if p["update"] > last["update"]]
    assert later and kept["discounted_return"] == max([best_pt["best_eval"]["discounted_return"], *later])


def test_an_early_stopped_run_resumed_with_its_patience_trains_nothing(tmp_path):
    """Bug: the early stop was checked after an update, so resuming an early-stopped run trained one more batch
    (validated or not)."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    train(_cfg("collector.total_frames=128"), run)
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    save_checkpoint(run / "checkpoints" / "last.pt", {k: v for k, v in {**last, "evals_since_best": 2}.items()
                                                        if k not in ("kind", "format_version", "sha256")})
    resumed = train(_cfg("collector.total_frames=256", "eval.patience=2",
                         f"checkpoint.resume={run / 'checkpoints' / 'last.pt'}"), tmp_path / "resumed")
    assert resumed["frames"] == last["frames"] and resumed["updates"] == last["update"]
    assert resumed["stopped_early"]


def test_a_resume_with_nothing_to_train_reports_the_last_evaluation(tmp_path):
    """Bug: ``final_eval`` was null after a resume that evaluated nothing (it was not in the checkpoint)."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    first = train(_cfg(), run)
    again = train(_cfg(f"checkpoint.resume={run / 'checkpoints' / 'last.pt'}"), tmp_path / "again")
    assert again["final_eval"] == first["final_eval"] and again["final_eval"] is not None


def test_best_pt_ends_its_curve_with_its_own_point(tmp_path):
    """Bug: best.pt's curve lacked its own point (saved before the point was appended): a run resumed from best.pt
    lost the best evaluation from its curve."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    train(_cfg("collector.total_frames=128"), run)
    best_pt = load_checkpoint(run / "checkpoints" / "best.pt")
    assert best_pt["curve"][-1]["update"] == best_pt["update"] == best_pt["best_eval"]["update"]
    assert json.loads((run / "summary.json").read_text())["curve"][:len(best_pt["curve"])] == best_pt["curve"]


@pytest.fixture
def late_background(monkeypatch):
    """A background pass whose result comes at the next iteration, not in the one that submitted it."""
    results, submit = validation_module.BackgroundValidation.results, validation_module.BackgroundValidation.submit
    state = {"fresh": False}

    def late_submit(self, weights, tag):
        state["fresh"] = True
        return submit(self, weights, tag)

    def late_results(self, wait: bool = False):
        fresh, state["fresh"] = state["fresh"], False
        return [] if not wait and fresh else results(self, wait=True)

    monkeypatch.setattr(validation_module.BackgroundValidation, "submit", late_submit)
    monkeypatch.setattr(validation_module.BackgroundValidation, "results", late_results)


def test_a_pending_pass_best_pt_already_holds_counts_no_miss(tmp_path, crash_at, late_background):
    """A review's finding: last.pt saved with update 2's pass pending, its result (a new best) written to best.pt,
    then a crash. The resume took best.pt's record and re-ran the pass, which counted as a miss: with patience 1 the
    resumed run stopped at once."""
    torch.set_num_threads(1)
    run, common = tmp_path / "run", ["collector.total_frames=256", "eval.interval=2", "checkpoint.interval=2"]
    crash_at(4)
    with pytest.raises(Crash):
        train(_cfg(*common, "eval.background=true"), run)
    last = load_checkpoint(run / "checkpoints" / "last.pt")
    assert [tag["update"] for tag in last["pending"]] == [2] and load_checkpoint(
        run / "checkpoints" / "best.pt")["best_eval"]["update"] == 2
    resumed = train(_cfg(*common, "eval.patience=1", f"checkpoint.resume={run / 'checkpoints' / 'last.pt'}"),
                    tmp_path / "resumed")
    assert resumed["frames"] > last["frames"]  # the pass is the best so far: patience 1 is not used up


def test_ctrl_c_while_a_resumed_run_validates_its_pending_pass(tmp_path, crash_at, slow_background, monkeypatch):
    """A review's finding: the pending pass ran before the protocol's try block, so a Ctrl-C there wrote no
    summary.json and no last.pt and left the validation process running. Now the run ends as after any Ctrl-C,
    and its last.pt still holds the pass it did not finish."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    crash_at(6)
    with pytest.raises(Crash):
        train(_cfg("collector.total_frames=256", "eval.background=true"), run)
    evaluate, calls = validation_module.evaluate, {"n": 0}

    def interrupted_once(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:
            raise KeyboardInterrupt
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(validation_module, "evaluate", interrupted_once)
    processes, init = [], validation_module.BackgroundValidation.__init__

    def tracked(self, *args, **kwargs):
        init(self, *args, **kwargs)
        processes.append(self)

    monkeypatch.setattr(validation_module.BackgroundValidation, "__init__", tracked)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg("collector.total_frames=256", "eval.background=true",
                   f"checkpoint.resume={run / 'checkpoints' / 'last.pt'}"), tmp_path / "resumed")
    assert json.loads((tmp_path / "resumed" / "summary.json").read_text())["interrupted"]
    assert [t["update"] for t in load_checkpoint(tmp_path / "resumed" / "checkpoints" / "last.pt")["pending"]] == [5]
    assert processes and all(p.proc.poll() is not None for p in processes)


def test_a_second_ctrl_c_keeps_the_pending_pass_in_last_pt(tmp_path, monkeypatch):
    """A review's finding: a second Ctrl-C while the run waited for the queued pass left it unrecorded, and the
    final last.pt (written without it) dropped the pass the periodic one held."""
    torch.set_num_threads(1)
    results, state = validation_module.BackgroundValidation.results, {"interrupted": False}

    def impatient(self, wait: bool = False):
        if state["interrupted"] and wait:
            raise KeyboardInterrupt  # the second Ctrl-C
        return results(self, wait=True) if wait else []

    monkeypatch.setattr(validation_module.BackgroundValidation, "results", impatient)
    cls, calls = get_algorithm("ppo"), {"n": 0}
    iterate = cls.iterate

    def first_ctrl_c(self, remaining):
        calls["n"] += 1
        if calls["n"] == 6:
            state["interrupted"] = True
            raise KeyboardInterrupt
        return iterate(self, remaining)

    monkeypatch.setattr(cls, "iterate", first_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg("collector.total_frames=256", "eval.background=true"), tmp_path / "run")
    last = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    assert [t["update"] for t in last["pending"]] == [5] and last["curve"][-1]["update"] == 4
