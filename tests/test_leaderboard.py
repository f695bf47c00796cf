"""The leaderboard puts trained runs on the gap table's own states: same states, same T and γ, ratios to the
optimum and gain share computed from the table's rows, runs of one (algorithm, training env) merged over seeds."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from anm_torchrl.experiments import leaderboard


def _run_dir(tmp_path, ckpt, name, frames=32, track_seconds=None):
    d = tmp_path / name
    (d / "checkpoints").mkdir(parents=True)
    shutil.copy(ckpt, d / "checkpoints" / "best.pt")
    summary = {"frames": frames, "wall_time": 12.5, "stopped_early": False}
    if track_seconds is not None:  # a gradient-study cell: the test states tracked during training
        summary["track_seconds"] = track_seconds
    (d / "summary.json").write_text(json.dumps(summary))
    return d


def test_trained_runs_are_scored_on_the_tables_states(ppo_checkpoint, tmp_path):
    protocol = {"network": "anm6_easy", "episodes": 2, "seed": 0, "steps": 5, "gamma": 0.995}
    table = {"protocol": protocol, "rows": [
        {"policy": "optimum", "row": "optimal", "discounted_return": -1.0, "states": 2, "source": "gap"},
        {"policy": "do-nothing", "row": "do_nothing", "discounted_return": -9.0, "states": 2, "source": "gap"},
        {"policy": "AC-MPC on #0", "row": "acmpc_16", "discounted_return": -2.0, "states": 1, "source": "gap"}]}
    runs = [_run_dir(tmp_path, ppo_checkpoint, "a"),
            _run_dir(tmp_path, ppo_checkpoint, "b", frames=64, track_seconds=2.5)]
    rec = leaderboard.build("anm6_easy", runs, gap_table=table)
    rows = {r["row"]: r for r in rec["rows"]}
    assert set(rows) == {"optimal", "do_nothing", "ppo_none"}  # a row on 1 of 2 states does not compare
    ppo = rows["ppo_none"]
    assert ppo["seeds"] == [0, 0] and ppo["frames"] == 48 and ppo["std_over_seeds"] == 0.0  # same checkpoint twice
    assert ppo["wall_s"] == 11.25  # 12.5 s and 12.5 - 2.5 s: a study's test tracking is not the recipe's time

    from anm_torchrl.evaluation import draw_initial_states, evaluate_policy
    from anm_torchrl.training.checkpoint import load_actor

    direct = evaluate_policy(load_actor(ppo_checkpoint), draw_initial_states(2, 0), max_steps=5, gamma=0.995)
    assert math.isclose(ppo["discounted_return"], float(direct.discounted_returns.mean()), rel_tol=1e-9)
    assert math.isclose(ppo["loss_ratio"], ppo["discounted_return"] / -1.0)
    assert math.isclose(ppo["gain_pct"], 100 * (ppo["discounted_return"] + 9.0) / 8.0)
    assert "| PPO trained on the true env |" in leaderboard.markdown(rec)


def test_a_run_of_another_network_is_refused(ppo_checkpoint, tmp_path):
    table = {"protocol": {"network": "case33bw", "episodes": 1, "seed": 0, "steps": 3, "gamma": 0.995}, "rows": []}
    with pytest.raises(ValueError, match="trained on 'anm6_easy', the table is of 'case33bw'"):
        leaderboard.build("case33bw", [_run_dir(tmp_path, ppo_checkpoint, "a")], gap_table=table)


def test_keep_takes_the_other_groups_runs_of_an_earlier_record_of_the_same_protocol(tmp_path, monkeypatch):
    protocol = {"network": "anm6_easy", "episodes": 2, "seed": 0, "steps": 5, "gamma": 0.995}
    table = {"protocol": protocol, "rows": [
        {"policy": "optimum", "row": "optimal", "discounted_return": -1.0, "states": 2, "source": "gap"},
        {"policy": "do-nothing", "row": "do_nothing", "discounted_return": -9.0, "states": 2, "source": "gap"}]}
    old = {"algorithm": "sac", "surrogate": "none", "seed": 0, "discounted_return": -8.0, "true_env_frames": 10,
           "wall_s": 3.0}
    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"protocol": protocol, "runs": [
        {"algorithm": "ppo", "surrogate": "none", "seed": 0, "discounted_return": -2.0, "true_env_frames": 10,
         "wall_s": 1.0}, old]}))
    kept = {"keep": json.loads(earlier.read_text()), "keep_source": str(earlier)}
    rec = leaderboard.build("anm6_easy", [], gap_table=table, **kept)
    assert {r["row"] for r in rec["rows"]} == {"optimal", "do_nothing", "ppo_none", "sac_none"}
    assert all(r["kept_from"] == str(earlier) for r in rec["runs"])
    assert len(rec["runs"]) == 2
    # a group given again is replaced, not merged with its earlier runs
    monkeypatch.setattr(leaderboard, "evaluate_run", lambda d, p: {**old, "seed": 5})
    again = leaderboard.build("anm6_easy", [tmp_path / "sac_run"], gap_table=table, **kept)
    assert [(r["algorithm"], r["seed"]) for r in again["runs"]] == [("ppo", 0), ("sac", 5)]
    assert "kept_from" in again["runs"][0] and "kept_from" not in again["runs"][1]
    monkeypatch.undo()
    other = {**protocol, "steps": 6}
    with pytest.raises(ValueError, match="cannot be kept"):  # before any run is evaluated (this one does not exist)
        leaderboard.build("anm6_easy", [tmp_path / "no_run"], gap_table={**table, "protocol": other}, **kept)


def test_the_cli_names_a_kept_file_it_cannot_read(tmp_path):
    from anm_torchrl.cli import leaderboard as cli

    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="--keep .*bad.json: not a readable JSON record"):
        cli.main(["--network", "anm6_easy", "--keep", str(tmp_path / "bad.json")])


def test_a_run_through_a_models_gradients_says_so_and_shows_its_model_frames():
    runs = [{"algorithm": "shac", "surrogate": s, "seed": 0, "discounted_return": -1.0, "true_env_frames": 0,
             "model_frames": 1000, "wall_s": 1.0} for s in ("none", "pinn")]
    rows = {r["row"]: r for r in leaderboard.trained_rows(runs)}
    assert rows["shac_none"]["policy"] == "SHAC through the exact simulator's gradients"
    assert rows["shac_pinn"]["policy"] == "SHAC through the pinn surrogate's gradients"
    for r in rows.values():
        r.update(loss_ratio=1.0, gain_pct=100.0)
    text = leaderboard.markdown({"network": "anm6_easy", "rows": list(rows.values()),
                                 "protocol": {"episodes": 1, "seed": 0, "steps": 5, "gamma": 0.995}})
    assert "| 0 (1,000 model) |" in text


def test_a_warm_started_run_is_its_own_row_with_its_teachers_model_frames():
    base = {"algorithm": "ppo", "surrogate": "pinn", "seed": 0, "true_env_frames": 0, "model_frames": None,
            "wall_s": 1.0}
    runs = [{**base, "discounted_return": -2.0},
            {**base, "discounted_return": -1.0, "warm_start": "shac", "warm_start_model_frames": 5000}]
    rows = {r["row"]: r for r in leaderboard.trained_rows(runs)}
    assert rows["ppo_pinn"]["policy"] == "PPO trained on the pinn surrogate"
    assert rows["ppo_pinn"]["model_frames"] is None
    warm = rows["ppo_pinn_from_shac"]
    assert warm["policy"] == "PPO trained on the pinn surrogate, started from SHAC through its gradients"
    assert warm["model_frames"] == 5000 and warm["discounted_return"] == -1.0
