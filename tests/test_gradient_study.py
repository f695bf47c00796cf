"""The time-to-threshold study (anm_torchrl.experiments.gradient_study) and the learning curve it reads: the
protocol's tracked test returns (eval.track_test), thresholds from the gap tables, censored times, the generated
verdict and the docs block that must equal its rendering from the committed records."""

from __future__ import annotations

import json
import logging
import math
import shutil
from pathlib import Path

import pytest

from anm_torchrl.experiments import cells
from anm_torchrl.experiments import gradient_study as gs
from anm_torchrl.experiments.leaderboard import gap_table_path
from tests.test_recipes_ppo import ROOT, run, scalars
from tests.test_recipes_shac import SHAC, TINY_SHAC

PROTOCOL = {"episodes": 2, "seed": 0, "steps": 5, "gamma": 0.995}


GAP = {"protocol": PROTOCOL, "rows": [
    {"policy": "optimum", "row": "optimal", "discounted_return": -1.0, "states": 2, "source": "gap"},
    {"policy": "do-nothing", "row": "do_nothing", "discounted_return": -9.0, "states": 2, "source": "gap"}]}
#: every cell key of the tiny SHAC run but the test states', which the campaign sets from the gap table
TINY = tuple(k for k in TINY_SHAC if not k.startswith("eval.test_episodes="))


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """A one-cell campaign (tiny SHAC on ANM6-Easy, a 2-state, 5-step gap table): its record and the runs folder."""
    tmp = tmp_path_factory.mktemp("study")
    (tmp / "gap.json").write_text(json.dumps(GAP))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(gs, "gap_table_path", lambda network: tmp / "gap.json")
        record = gs.campaign("anm6_easy", ["shac_exact"], [0], tmp / "runs", jobs=1, overrides=TINY)
    return record, (tmp / "runs").resolve(), tmp / "gap.json"


@pytest.fixture(scope="module")
def tracked_run(campaign) -> Path:
    return campaign[1] / "anm6_easy_shac_exact_s0"


def test_a_tracked_run_records_its_curve_on_the_test_states(tracked_run):
    summary = json.loads((tracked_run / "summary.json").read_text())
    curve = summary["curve"]
    assert [p["frames"] for p in curve] == [32, 64], "one point per validation (eval.interval=1, 2 iterations)"
    assert all(p["true_env_frames"] == 0 for p in curve), "SHAC trains on its model: 0 true-env frames"
    assert all(math.isfinite(p["test"]) and math.isfinite(p["validation"]) for p in curve)
    assert curve[0]["wall_s"] < curve[1]["wall_s"] and summary["track_seconds"] > 0
    assert "track/discounted_return" in scalars(tracked_run)
    run_ = gs.read_run(tracked_run, PROTOCOL)
    assert run_["frames"] == 64 and run_["true_env_frames"] == 0 and run_["budget_unit"] == "model_frames"
    with pytest.raises(ValueError, match="not a study cell"):
        gs.read_run(tracked_run, {**PROTOCOL, "steps": 3000})


def test_tracking_is_checked_like_every_key():
    from hydra import compose, initialize_config_dir

    from anm_torchrl.training.algorithms import check_algorithm_config

    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "conf"), version_base="1.3"):
        cfg = compose(config_name="shac", overrides=[*TINY_SHAC, "eval.track_test=sometimes"])
    with pytest.raises(ValueError, match="eval.track_test must be one of false, true; got 'sometimes'"):
        check_algorithm_config(cfg)


def test_thresholds_come_from_the_gap_tables():
    anm6 = json.loads(gap_table_path("anm6_easy").read_text())
    opt = next(r["discounted_return"] for r in anm6["rows"] if r["row"] == "optimal")
    assert [t["return"] for t in gs.thresholds("anm6_easy", anm6)] == pytest.approx([1.5 * opt, 1.1 * opt])
    feeder = json.loads(gap_table_path("case33bw").read_text())
    by = {r["row"]: r["discounted_return"] for r in feeder["rows"] if r.get("source") == "gap"}
    t90, t97 = (t["return"] for t in gs.thresholds("case33bw", feeder))
    assert t90 == pytest.approx(by["do_nothing"] + 0.9 * (by["optimal"] - by["do_nothing"]))
    assert by["do_nothing"] < t90 < t97 < by["optimal"]


def test_a_cell_is_the_recipes_default_command_with_its_seed_and_the_tracking(tmp_path):
    cmd = gs.cell_command("shac_pinn", "case33bw", 2, tmp_path / "r", PROTOCOL, tmp_path / "p.safetensors")
    assert cmd[1].endswith("recipes/shac.py") and "seed=2" in cmd and "network=case33bw" in cmd
    assert {"model=pinn", "surrogate=pinn", f"surrogate.path={tmp_path / 'p.safetensors'}", "eval.track_test=true",
            "eval.test_episodes=2", "eval.test_seed=0", "eval.test_max_steps=5"} <= set(cmd)
    assert cells.shown(cmd).startswith("python recipes/shac.py network=case33bw seed=2 model=pinn")


def _curve(tests: list[float], step: int = 100) -> list[dict]:
    return [{"frames": step * (i + 1), "true_env_frames": 0, "wall_s": 10.0 * (i + 1), "validation": t, "test": t}
            for i, t in enumerate(tests)]


def test_times_to_a_threshold_count_runs_that_never_reach_it_as_censored():
    levels = [{"name": "a", "return": -2.0}, {"name": "b", "return": -1.0}]
    runs = [{"curve": _curve([-5, -3, -1.5])}, {"curve": _curve([-4, -1.8, -0.9, -0.8])}]
    a, b = gs.summarize(runs, levels, offset_s=100.0)
    assert a["per_seed"][0]["frames"] == 300 and a["per_seed"][1]["frames"] == 200
    assert a["wall_s"]["median"] == 120.0 and a["wall_s"]["reached"] == 2, "KM median of 120 s and 130 s (+100 s)"
    # b: one run reaches it at 30 s (+100), the other is censored at its end (30 s + 100): the median is the event
    assert b["frames"]["reached"] == 1 and b["frames"]["censored_at"] == [300] and b["frames"]["median"] == 300


def _record(network: str, shac_frames: list[float | None], ppo_frames: list[float | None]) -> dict:
    def row(method, frames):
        th = {"wall_s": {"median": None if frames[0] is None else frames[0] / 10, "reached": 3, "runs": 3},
              "frames": {"median": frames[0], "reached": 3 if frames[0] else 1, "runs": 3}}
        return {"method": method, "label": gs.METHODS[method][2], "runs": [],
                "thresholds": [{**th, "threshold": "t1"}]}
    return {"network": network, "thresholds": [{"name": "1.5× the optimum's loss"}],
            "methods": [row("shac_exact", shac_frames), row("ppo", ppo_frames)]}


def test_the_verdict_says_how_many_times_fewer_transitions_or_that_it_was_not_reached():
    text = gs.verdict([_record("anm6_easy", [1e5], [1e6])])
    assert "10× fewer transitions" in text and "anm6_easy, 1.5× the optimum's loss" in text
    slower = gs.verdict([_record("anm6_easy", [1e5], [1e4])])
    assert "10× more transitions, PPO 10× faster in wall time" in slower
    # a factor that rounds to 1 (here 1.03) is said as such, not as "1× faster"
    same = gs.verdict([_record("anm6_easy", [1.03e5], [1e5])])
    assert "as many transitions, as fast in wall time" in same and "1×" not in same
    assert "reached by fewer than half its runs (1/3)" in gs.verdict([_record("anm6_easy", [None], [1e6])])
    assert "PPO did not within its budget" in gs.verdict([_record("anm6_easy", [1e5], [None])])


def test_the_verdict_reads_the_frames_to_ppos_best_return_off_the_test_curves():
    """PPO's best is the mean of its best.pt test returns (-1.0 here); PPO's curves reach it at 2,000 and 3,000
    frames (KM median 3,000 over 3 runs, one censored), SHAC's at 100 and 200 (median 200): 15x fewer."""
    ppo = [{"curve": _curve([-3, -2, -1.0], step=1000), "test_best": -1.0},
           {"curve": _curve([-3, -0.5], step=1000), "test_best": -0.5},
           {"curve": _curve([-3, -2, -1.5], step=1000), "test_best": -1.5}]
    shac = [{"curve": _curve([-2, -0.9]), "test_best": -0.9}, {"curve": _curve([-0.8]), "test_best": -0.8},
            {"curve": _curve([-3, -2]), "test_best": -2.0}]
    rec = {"network": "case33bw", "methods": [{"method": "shac_exact", "label": "SHAC", "runs": shac},
                                               {"method": "ppo", "label": "PPO", "runs": ppo}]}
    (line,) = gs.ppo_best_lines(rec)
    assert "PPO's best return (-1, the mean of its best.pt test returns): SHAC reached it in 2/3 runs" in line
    assert "median 200 model frames against PPO's 3,000 true-env frames (2/3 runs): 15× fewer" in line
    shac_slow = [{**r, "curve": _curve([-3] * 39 + [-0.5])} for r in shac]  # each reaches it at 4,000 frames
    (line,) = gs.ppo_best_lines({**rec, "methods": [{"method": "shac_exact", "label": "SHAC", "runs": shac_slow},
                                                    rec["methods"][1]]})
    assert "against PPO's 3,000 true-env frames (2/3 runs): 1.3× more transitions (issue 26's target: 10× fewer)" \
        in line
    shac[0]["curve"], shac[1]["curve"] = _curve([-2]), _curve([-2])
    assert "reached it in 0/3 runs, fewer than half (PPO's own runs: 2/3)" in gs.ppo_best_lines(rec)[0]
    assert gs.ppo_best_lines({"network": "x", "methods": [{"method": "shac_exact", "runs": shac}]}) == []


def test_the_docs_block_is_refused_on_a_page_without_it_and_rewritten_in_place(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# results\n")
    with pytest.raises(ValueError, match="no <!-- gradients:begin"):
        gs.update_page(page, [])
    page.write_text(f"before\n{gs.MARKERS[0]}\nstale\n{gs.MARKERS[1]}\nafter\n")
    gs.update_page(page, [])
    text = page.read_text()
    assert "stale" not in text and text.startswith("before\n") and text.endswith("after\n")
    assert "When does a differentiable model pay off?" in text


def test_the_committed_docs_block_is_rendered_from_the_committed_records():
    records = [json.loads(p.read_text()) for p in sorted((ROOT / "results" / "gradient_study").glob("*.json"))]
    text = (ROOT / "docs" / "RESULTS.md").read_text()
    start, end = text.index(gs.MARKERS[0]) + len(gs.MARKERS[0]) + 1, text.index(gs.MARKERS[1])
    if not records:
        pytest.skip("no study record committed yet")
    assert text[start:end] == gs.render(records)


def test_the_cli_refuses_a_bad_job_count(capsys):
    from anm_torchrl.cli import gradient_study as cli

    with pytest.raises(SystemExit):
        cli.main(["--jobs", "0"])
    assert "argument --jobs: must be an integer >= 1, got 0" in capsys.readouterr().err


def test_a_campaign_reuses_finished_cells_and_renders_its_record(campaign, monkeypatch):
    record, runs, gap = campaign
    assert record["failed"] == [] and record["optimum"] == -1.0 and record["overrides"] == list(TINY)
    (row,) = record["methods"]
    assert row["command"].startswith("python recipes/shac.py network=anm6_easy seed=0 model=exact")
    assert row["runs"][0]["process_wall_s"] > 0 and len(row["runs"][0]["load_avg_1min"]) == 2
    table = gs.markdown(record)
    assert "| SHAC through the exact simulator's gradients | 1.5× the optimum's loss |" in table
    assert "(model) |" in table and "load average at the cells' starts and ends" in table
    assert gs.render([record]).count("| SHAC through") == 2
    # the same campaign again: the finished cell is read back, never re-trained
    monkeypatch.setattr(gs, "gap_table_path", lambda network: gap)
    monkeypatch.setattr(cells, "ProcessPoolExecutor", lambda *a, **k: pytest.fail("a finished cell was run again"))
    again = gs.campaign("anm6_easy", ["shac_exact"], [0], runs, jobs=1, overrides=TINY)
    assert again["methods"][0]["runs"] == row["runs"]


def test_a_kept_record_keeps_the_rows_not_re_made(campaign, monkeypatch):
    """``keep``: one method's cells re-made after its defaults change, the other methods' rows kept as they were
    (marked with their source) in the methods' order; a record of other test states, seeds or overrides is refused
    by name, as is a file that is not this study's record."""
    record, runs, gap = campaign
    monkeypatch.setattr(gs, "gap_table_path", lambda network: gap)
    keep = json.loads(json.dumps(record))
    ppo = {**keep["methods"][0], "method": "ppo", "label": "PPO on the true env"}
    keep["methods"].append(ppo)
    again = gs.campaign("anm6_easy", ["shac_exact"], [0], runs, jobs=1, overrides=TINY, keep=keep,
                        keep_source="k.json")
    assert [r["method"] for r in again["methods"]] == ["shac_exact", "ppo"] and again["kept_from"] == "k.json"
    assert again["methods"][1] == {**ppo, "kept_from": "k.json"} and "kept_from" not in again["methods"][0]
    assert again["methods"][0]["runs"] == record["methods"][0]["runs"]  # re-made (here: read back), not kept
    assert "not re-run with the others): PPO on the true env." in gs.markdown(again)
    assert "Kept from" not in gs.markdown(record)
    for key, value in (("seeds", [0, 1]), ("overrides", []), ("protocol", {**PROTOCOL, "steps": 6})):
        with pytest.raises(ValueError, match=f"k.json: its {key} .* cannot be kept"):
            gs.campaign("anm6_easy", ["shac_exact"], [0], runs, jobs=1, overrides=TINY, keep={**keep, key: value},
                        keep_source="k.json")
    with pytest.raises(ValueError, match="k.json: not a record of the gradient study"):
        gs.campaign("anm6_easy", ["shac_exact"], [0], runs, jobs=1, overrides=TINY, keep={"networks": []},
                    keep_source="k.json")


def test_the_clis_refuse_a_kept_file_that_is_not_a_record(tmp_path):
    from anm_torchrl.cli.args import read_kept

    assert read_kept(None) is None
    (tmp_path / "list.json").write_text("[]")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="--keep .*list.json: not a record \\(a JSON list"):
        read_kept(str(tmp_path / "list.json"))
    for name in ("bad.json", "missing.json"):
        with pytest.raises(ValueError, match=f"--keep .*{name}: not a readable JSON record"):
            read_kept(str(tmp_path / name))


def test_a_cell_trained_at_another_config_is_trained_again(campaign, tmp_path, caplog):
    """The same command line at a changed default (e.g. a new per-network entry) must not reuse the old run."""
    cell = tmp_path / "cell"
    shutil.copytree(campaign[1] / "anm6_easy_shac_exact_s0", cell)
    marker = json.loads((cell / "study_cell.json").read_text())
    command = [f"hydra.run.dir={cell}" if a.startswith("hydra.run.dir=") else a for a in marker["command"]]
    (cell / "study_cell.json").write_text(json.dumps({**marker, "command": command}))
    assert cells.finished(command, cell)
    summary = json.loads((cell / "summary.json").read_text())
    summary["config"]["per_network"]["case33bw"] = {"env": {"num_envs": 7}}  # another network's entry: no change here
    (cell / "summary.json").write_text(json.dumps(summary))
    assert cells.finished(command, cell)
    summary["config"]["loss"]["horizon"] += 1
    (cell / "summary.json").write_text(json.dumps(summary))
    with caplog.at_level(logging.INFO, logger=cells.__name__):
        assert not cells.finished(command, cell)
    assert "was trained with another config (loss.horizon): trained again" in caplog.text


def test_the_campaigns_pinn_is_reused_only_if_trained_on_the_same_network_with_the_same_preset(tmp_path,
                                                                                               monkeypatch):
    from anm_torchrl.surrogates.pinn import cache

    trained = []

    def fake_train(cfg, sim, path):
        import torch

        assert torch.get_num_threads() == 1, "trained on one thread, as the recipes"
        trained.append(cfg)
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_bytes(b"weights")

    monkeypatch.setattr(cache, "train_and_save", fake_train)
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(2)  # a caller on two threads: the training's one must not leak back to it
    try:
        gs.train_pinn("anm6_easy", tmp_path / "pinn")
        assert torch.get_num_threads() == 2, "the caller's thread count is given back"
    finally:
        torch.set_num_threads(before)
    gs.train_pinn("anm6_easy", tmp_path / "pinn")
    assert len(trained) == 1, "the second call reuses the first's PINN"
    marker = tmp_path / "pinn" / "study_pinn.json"
    kept = json.loads(marker.read_text())
    marker.write_text(json.dumps({**kept, "network_key": "another network's data"}))
    gs.train_pinn("anm6_easy", tmp_path / "pinn")
    assert len(trained) == 2 and json.loads(marker.read_text())["network_key"] == kept["network_key"]


def test_a_failed_cell_is_reported_with_its_error(tmp_path):
    run_dir = tmp_path / "bad"
    (run_dir / "logs").mkdir(parents=True)
    (run_dir / "logs" / "stale").write_text("an unfinished earlier attempt")
    command = gs.cell_command("shac_exact", "anm6_easy", 0, run_dir, PROTOCOL, None, ("loss.horizon=0",))
    (out,) = gs.run_cells({run_dir: command}, jobs=1)
    assert "loss.horizon must be an integer >= 1, got 0" in out["error"]
    assert not (run_dir / "study_cell.json").exists() and not (run_dir / "logs" / "stale").exists()


def test_a_cell_stopped_by_a_signal_is_a_failure_not_a_finished_cell(tmp_path, monkeypatch):
    """A cell whose run ended as interrupted (a Ctrl-C, or the SIGTERM it sends itself when its study has gone)
    raises instead of returning its marker: the study reports it, and the next run trains it again."""
    import signal

    from anm_torchrl.training import protocol, signals
    from tests.test_signals import _deliver

    def interrupted_run(cfg, run_dir, network_defaults=None):
        with signals.graceful():
            _deliver(signal.SIGTERM)  # asks: the loop would finish its iteration, then end
        return None

    monkeypatch.setattr(signals, "stop_when_orphaned", lambda: None)  # no watch thread left in the test process
    monkeypatch.setattr(cells, "cell_config", lambda command: (None, None))
    monkeypatch.setattr(cells, "network_key", lambda cfg: "key")
    monkeypatch.setattr(protocol, "train", interrupted_run)
    with pytest.raises(RuntimeError, match="stopped by SIGTERM \\(interrupted, not a finished cell\\)"):
        cells.train_cell(["python", "ppo.py"], tmp_path / "cell")
