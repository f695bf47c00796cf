"""The reproduction pipeline end to end on the ``tiny`` preset, then the notebooks against its results."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# ~2 min: the whole pipeline plus three notebook kernels; part of the default run (issue: notebooks tested in CI)

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = ["paper_figures.ipynb", "beyond_paper.ipynb", "composable_parts.ipynb"]
EXPERIMENTS = ["pinn_losses", "speed", "accuracy", "rollout_error", "adaptability", "sweep", "ppo_curves",
               "test_returns"]


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    typed_in = tmp_path_factory.mktemp("typed_in")
    out = typed_in / "reproduce"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ANM_TORCHRL_HOME": str(out / "home")}
    # out_dir relative to where the command is typed, and the run's only folder: Hydra's log goes there too (it went
    # to ./outputs/reproduce, and a relative out_dir was taken relative to the repository)
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), "preset=tiny", "out_dir=reproduce",
                           f"results_md={out / 'RESULTS.md'}"], cwd=typed_in, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert (out / "reproduce.log").is_file() and not (typed_in / "outputs").exists()
    return out


def test_reproduce_writes_every_record(results: Path):
    run = json.loads((results / "run.json").read_text())
    assert set(run["experiments"]) == set(EXPERIMENTS)
    assert run["machine"]["usable_cores"] >= 1 and run["versions"]["torch"]
    for name in EXPERIMENTS:
        rec = json.loads((results / f"{name}.json").read_text())
        assert rec["status"] in ("ok", "partial", "not available"), (name, rec["reason"])
        assert rec["meta"]["wall_s"] >= 0 and "machine" in rec["meta"]
    speed = json.loads((results / "speed.json").read_text())["data"]
    assert {r["impl"] for r in speed["table"]} >= {"gym_anm", "anm6env", "anm6env_torch", "grid_sim"}
    assert len(speed["load_avg_1min"]) == 2 and min(speed["load_avg_1min"]) >= 0.0  # before / after the timings
    assert (results / "speed_table.csv").exists() and (results / "figures" / "fig6_speed.png").exists()


def test_results_md_is_generated(results: Path):
    md = (results / "RESULTS.md").read_text()
    assert "do not edit by hand" in md and md.count("| **") >= 4
    # a run's own page names its own records (it named the published results/reproduction/ ones)
    assert f"records under `{results}`" in md and "_From `results/" not in md
    for title in ("Fig. 5", "Fig. 6", "Fig. 7", "Figs. 8–9", "Figs. 10–11", "PPO training curves"):
        assert title in md


def test_report_only_rewrites_the_page_from_the_records(results: Path):
    """``report_only=true`` runs nothing: same records, a page rendered again from them."""
    md = results / "RESULTS_again.md"  # beside the original, so figure links compare equal
    records = {p.name: p.read_bytes() for p in results.glob("*.json")}
    env = {**os.environ, "ANM_TORCHRL_HOME": str(results / "home")}  # the home of the run: paths shown relative to it
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), f"out_dir={results}",
                           f"results_md={md}", "report_only=true", f"hydra.run.dir={results / 'hydra_again'}"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert records == {p.name: p.read_bytes() for p in results.glob("*.json")}
    assert md.read_text().split("\n", 3)[3] == (results / "RESULTS.md").read_text().split("\n", 3)[3]


def test_a_partial_rerun_into_a_run_directory_needs_merge(results: Path):
    """A run of some experiments into a run directory holding an earlier run's records would list only its own in
    run.json while the page showed both: refused, before anything runs, without merge=true."""
    before = (results / "run.json").read_bytes()
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), "preset=tiny",
                           "preset.experiments=[speed]", f"out_dir={results}"], cwd=REPO,
                          env={**os.environ, "ANM_TORCHRL_HOME": str(results / "home")}, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "holds an earlier run's records of" in proc.stderr and "merge=true" in proc.stderr
    assert (results / "run.json").read_bytes() == before


@pytest.mark.parametrize("notebook", NOTEBOOKS)
def test_notebook_runs(results: Path, notebook: str, tmp_path: Path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("ANM_RESULTS_DIR", str(results))
    monkeypatch.setenv("ANM_FIGURES_DIR", str(tmp_path / "figs"))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    nb = nbformat.read(REPO / "notebooks" / notebook, as_version=4)
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(REPO / "notebooks")}}).execute()


def test_accuracy_rows_name_the_dataset_evaluated_on(tmp_path: Path):
    """A cross-dataset entry is labelled with the other dataset (the one it was evaluated on)."""
    from anm_torchrl.experiments.accuracy import rows_from_metrics

    m = {"kind": "xgb", "dataset": "agent", "in_dataset": {"r2": 0.99, "mae": 0.1},
         "cross_dataset": {"dataset": "generative", "r2": 0.7, "mae": 0.9}}
    path = tmp_path / "xgb_agent" / "metrics.json"
    path.parent.mkdir()
    path.write_text(json.dumps(m))
    rows = {r["split"]: r for r in rows_from_metrics(path)}
    assert (rows["in_dataset"]["eval_dataset"], rows["in_dataset"]["cross"]) == ("agent", False)
    assert (rows["cross_dataset"]["eval_dataset"], rows["cross_dataset"]["cross"]) == ("generative", True)
    assert rows["cross_dataset"]["r2"] == 0.7 and rows["cross_dataset"]["train_dataset"] == "agent"


def test_accuracy_records_what_shaped_each_model(tmp_path: Path):
    """The accuracy record names each model's dataset (checksum) and the training budget it reached, read from the
    surrogate.json beside its metrics (a DNN cut short by wall time was invisible in the metrics alone)."""
    from anm_torchrl.experiments import accuracy
    from anm_torchrl.experiments.common import RunContext

    folder = tmp_path / "dnn_agent"
    folder.mkdir()
    (folder / "metrics.json").write_text(json.dumps({"kind": "dnn", "dataset": "agent",
                                                     "in_dataset": {"r2": 0.99, "mae": 0.16}}))
    ds = {"kind": "agent", "size": 100000, "seed": 0, "checksum": "b525b868"}
    (folder / "surrogate.json").write_text(json.dumps({
        "dataset_meta": ds, "simulator": {"network_key": "k1"}, "seed": 0, "params": {"max_epochs": 150},
        "train_info": {"epochs": 150, "stop": "max_epochs", "params": {"max_epochs": 150}}}))
    rec = accuracy.run({"paths": [str(folder / "metrics.json")]}, RunContext(out_dir=tmp_path))
    m = rec["data"]["models"]["dnn_agent"]
    assert m["dataset_meta"] == ds and m["network_key"] == "k1"
    assert m["train_info"] == {"epochs": 150, "stop": "max_epochs"}  # hyper-parameters once, under "params"


def test_run_ppo_starts_from_an_empty_run_dir(tmp_path: Path, monkeypatch):
    """Logs left by an earlier run of the same cell are not read back as part of the new run's curve; the run is
    the recipe's loop called in-process (no subprocess), and a failing run is recorded with its error."""
    from anm_torchrl.experiments import ppo_runs
    from anm_torchrl.training import protocol

    stale = tmp_path / "cell"
    (stale / "logs").mkdir(parents=True)
    (stale / "summary.json").write_text("{}")
    seen = {}

    def fake_train(cfg, run_dir, network_defaults=None):
        seen["existed"], seen["surrogate"] = stale.exists(), cfg.surrogate.name
        seen["max_minutes"] = cfg.collector.max_minutes
        raise RuntimeError("boom")

    monkeypatch.setattr(protocol, "train", fake_train)
    rec = ppo_runs.run_ppo(["surrogate=none"], stale, timeout_s=90)
    assert seen == {"existed": False, "surrogate": "none", "max_minutes": 1.5}
    assert rec["summary"] is None and rec["curve"] == [] and not rec["ok"]
    assert rec["error"].startswith("RuntimeError: boom")


def test_no_shell_out_to_recipes():
    """The package calls library functions; its only subprocesses are ``git`` queries (run provenance) and second
    processes of the package's own modules, started in one place (``processes.ModuleProcess``: ``python -m
    <module>``) by the module itself (``__name__``: the PINN training's stage, the validation passes), never a
    recipe."""
    import re

    call = re.compile(r"(subprocess\.\w+|os\.system|os\.exec\w*|os\.spawn\w*)\(\s*(\S{0,8})")
    own = ("anm_torchrl/processes.py", "subprocess.Popen([sys.exe")
    offenders = [f"{p.relative_to(REPO)}: {m.group(0)}" for p in (REPO / "anm_torchrl").rglob("*.py")
                 for m in call.finditer(p.read_text())
                 if not m.group(2).startswith('["git"') and m.group(1) != "subprocess.SubprocessError"
                 and (str(p.relative_to(REPO)), m.group(0)) != own]
    assert offenders == []
    assert '[sys.executable, "-m", module' in (REPO / own[0]).read_text()
    users = {str(p.relative_to(REPO)) for p in (REPO / "anm_torchrl").rglob("*.py")
             if "(ModuleProcess)" in p.read_text() or "ModuleProcess(" in p.read_text()} - {own[0]}
    assert users == {"anm_torchrl/surrogates/pinn/loop.py", "anm_torchrl/training/validation.py"}
    for path in users:  # each starts itself, no recipe
        assert "super().__init__(__name__," in (REPO / path).read_text(), path


# ------------------------------------------------------------------------------------------ time to return
def test_km_median_counts_censored_runs():
    """Two of three seeds reach the threshold (272 s, 357 s), one is censored at its 391 s run length: the KM
    median is the second event (357 s, survival 1/3 after it), not the mean of the two that reached it (315 s)."""
    from anm_torchrl.experiments.time_to_return import censored_summary, km_median

    assert km_median([272.0, 357.0, 391.0], [True, True, False]) == 357.0
    assert km_median([100.0, 391.0, 400.0], [True, False, False]) is None  # fewer than half reached it
    runs = [{"time_to_threshold": {"wall_s": 272.0}, "curve": [{"wall_s": 300.0}]},
            {"time_to_threshold": {"wall_s": 357.0}, "curve": [{"wall_s": 430.0}]},
            {"time_to_threshold": {"wall_s": None}, "curve": [{"wall_s": 391.0}]}]
    s = censored_summary(runs, "wall_s", offset_s=100.0)
    assert (s["median"], s["reached"], s["runs"], s["censored_at"]) == (457.0, 2, 3, [491.0])
    assert s["restricted_mean"] == (372.0 + 457.0 + 491.0) / 3 and s["lower_bound"]


def test_claim_two_reports_both_views_and_censoring():
    from anm_torchrl.experiments.ppo_curves import threshold_columns
    from anm_torchrl.experiments.claims import claim_training_time

    def runs(times, length):
        return [{"time_to_threshold": {"wall_s": t, "frames": None if t is None else 1}, "curve": [
            {"wall_s": length, "frames": 10}]} for t in times]

    table = [{"env": "pinn", "seeds": 3, "last_mean_return": -200.0, "frames": 300_000,
              **threshold_columns(runs([20.0, 30.0, 40.0], 60.0), 150.0)},
             {"env": "gym_anm", "seeds": 3, "last_mean_return": -400.0, "frames": 300_000,
              **threshold_columns(runs([272.0, 357.0, None], 391.0), 0.0)}]
    what, verdict = claim_training_time({"ppo_curves": {"status": "ok", "data": {"table": table, "threshold": -430}}})
    assert "PINN, PPO alone 30 s" in what and "92 % less" in what  # 1 - 30/357
    assert "incl. its training (150 s) 180 s" in what and "50 % less" in what  # 1 - 180/357
    assert "gym_anm 357 s (2/3 seeds reached it)" in what
    assert verdict == "holds without the PINN's training counted; holds with the PINN's training counted"


# ------------------------------------------------------------------------------------------ publishing
def _tree_digest(*folders: Path) -> dict[str, str]:
    import hashlib

    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for f in folders for p in sorted(f.rglob("*"))
            if p.is_file()}


def test_quick_run_leaves_results_and_docs_untouched(tmp_path: Path):
    """A reproduction (here preset=quick, one cheap experiment) writes only into its run directory."""
    before = _tree_digest(REPO / "results", REPO / "docs") | _tree_digest(REPO / "README.md")
    run_dir = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ANM_TORCHRL_HOME": str(tmp_path / "home")}
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), "preset=quick",
                           "preset.experiments=[accuracy]", "preset.pinn.train_if_missing=null",
                           f"hydra.run.dir={run_dir}"], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert (run_dir / "accuracy.json").is_file() and (run_dir / "RESULTS.md").is_file()
    assert json.loads((run_dir / "run.json").read_text())["preset"] == "quick"
    assert _tree_digest(REPO / "results", REPO / "docs") | _tree_digest(REPO / "README.md") == before


def test_publish_refuses_a_quick_run_over_the_full_record(tmp_path: Path):
    """publish=true of another preset is refused before anything runs, and the committed record is untouched."""
    target = tmp_path / "results"
    (target / "reproduction").mkdir(parents=True)
    (target / "reproduction" / "run.json").write_text(json.dumps({"name": "run", "preset": "full", "experiments": {"accuracy": {}}}))
    before = _tree_digest(target)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ANM_TORCHRL_HOME": str(tmp_path / "home"), "HYDRA_FULL_ERROR": "1"}
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), "preset=quick",
                           "preset.experiments=[accuracy]", "preset.pinn.train_if_missing=null", "publish=true",
                           f"publish_dir={target}", f"publish_md={tmp_path / 'R.md'}", "publish_readme=false",
                           f"hydra.run.dir={tmp_path / 'run'}"], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode != 0 and "preset='full' record and this run is preset='quick'" in proc.stderr
    assert _tree_digest(target) == before and not (tmp_path / "R.md").exists()
    assert not list((tmp_path / "run").glob("*.json"))  # refused before any experiment ran (Hydra made the folder)


def test_check_publish_and_merge(tmp_path: Path):
    from anm_torchrl.experiments.io import write_json
    from anm_torchrl.experiments.publish import PublishRefused, check_publish, publish

    target = tmp_path / "results"
    write_json(target / "run.json", {"name": "run", "preset": "full", "experiments": {"a": {}, "b": {}}})
    write_json(target / "a.json", {"name": "a", "v": 1})
    write_json(target / "b.json", {"name": "b", "v": 1})
    with pytest.raises(PublishRefused, match="leaves out experiments"):
        check_publish(target, "full", ["b"], merge=False, force=False)
    check_publish(target, "full", ["b"], merge=True, force=False)  # a merged subset is fine
    check_publish(target, "quick", ["a", "b"], merge=False, force=True)  # forced
    run = tmp_path / "run"
    write_json(run / "b.json", {"name": "b", "v": 2})
    info = publish(run, target, {"preset": "full", "command": "c", "date": "d", "wall_s": 1.0, "versions": {},
                                 "experiments": {"b": {"status": "ok"}}}, merge=True)
    assert [json.loads((target / f"{n}.json").read_text())["v"] for n in "ab"] == [1, 2]
    assert set(info["experiments"]) == {"a", "b"} and info["updates"][-1]["experiments"] == {"b": {"status": "ok"}}
    # a folder of records another command assembled (results/payoff/, no run.json) is not replaced unasked: a
    # payoff run of one part replaced the committed three-part record
    payoff = tmp_path / "payoff"
    write_json(payoff / "payoff.json", {"name": "payoff", "parts": ["cost", "accuracy", "ppo"]})
    with pytest.raises(PublishRefused, match=r"holds committed records of \['payoff'\] without a run.json"):
        check_publish(payoff, "payoff", ["payoff"], merge=False, force=False)
    check_publish(payoff, "payoff", ["payoff"], merge=False, force=True)
    check_publish(tmp_path / "empty", "payoff", ["payoff"], merge=False, force=False)  # nothing there yet


# ------------------------------------------------------------------------------------------ README and records
def test_readme_blocks_are_rendered_from_the_committed_records():
    """README's result blocks equal what the committed records under results/ render (no hand-typed numbers)."""
    from anm_torchrl.experiments.readme_blocks import BLOCK, BLOCKS, render_readme
    from anm_torchrl.experiments.records import load_published

    text = (REPO / "README.md").read_text()
    assert {m.group("name") for m in BLOCK.finditer(text)} == set(BLOCKS)
    assert render_readme(text, load_published(REPO / "results")) == text


def test_docs_hold_no_machine_local_paths():
    for page in [REPO / "README.md", *(REPO / "docs").glob("RESULTS*.md")]:
        text = page.read_text()
        for local in ("/root/", "/home/", "/tmp/", "/work/", ".cache/anm_torchrl"):
            assert local not in text, (page.name, local)


# ------------------------------------------------------------------------------------------ adaptability
def test_scaled_simulator_drives_the_true_env():
    """The true env on a scaled / shifted simulator copy writes the changed loads into its next state."""
    import torch

    from anm_torchrl.envs import ANM6Env
    from anm_torchrl.experiments.common import set_state_and_step
    from anm_torchrl.experiments.rollout_error import _default_sim, scaled_simulator
    from anm_torchrl.evaluation import draw_initial_states

    s0, a = draw_initial_states(4, 0), torch.zeros(4, 6)
    base = set_state_and_step(ANM6Env(4, action_mode="clip"), s0, a)["state"]
    scaled = set_state_and_step(ANM6Env(4, action_mode="clip", sim=scaled_simulator(load=1.2)), s0, a)["state"]
    loads = [1, 3, 5]  # device P of the three loads (MW, negative = consumption), inside their limits at x1.2
    torch.testing.assert_close(scaled[:, loads], 1.2 * base[:, loads], rtol=1e-9, atol=0.0)  # float64 physics
    sim = _default_sim()
    shifted = scaled_simulator(shift=24)
    torch.testing.assert_close(shifted.load_series[:, 24:], sim.load_series[:, :-24], rtol=0.0, atol=0.0)


def test_reused_measurements_must_share_states(tmp_path: Path):
    """Runs or rows taken from an earlier record are refused when it was measured on other states (another
    threshold / protocol), and are marked with that record's commit when accepted."""
    from anm_torchrl.experiments.io import write_json
    from anm_torchrl.experiments.ppo_curves import reused_runs
    from anm_torchrl.experiments.heldout_returns import reused_rows

    meta = {"versions": {"git_commit": "abc1234"}}
    curves = write_json(tmp_path / "ppo_curves.json", {"name": "ppo_curves", "meta": meta, "data": {
        "threshold": -430.0, "runs": {"none": [{"seed": 0, "curve": []}]}}})
    assert reused_runs({"from": curves, "envs": ["none"]}, -430.0)["none"][0]["reused_from"]["git_commit"] == "abc1234"
    with pytest.raises(ValueError, match="differs"):
        reused_runs({"from": curves, "envs": ["none"]}, -431.0)  # 0.2 % apart: other states
    protocol = {"test_episodes": 8, "test_seed": 0, "max_steps": 3000, "gamma": 0.995}
    rec = write_json(tmp_path / "test_returns.json", {"name": "test_returns", "meta": meta, "data": {
        "protocol": protocol, "rows": [{"policy": "do_nothing", "discounted_return": -800.0}], "runs": {}}})
    rows, _ = reused_rows([rec], protocol)
    assert rows[0]["discounted_return"] == -800.0 and rows[0]["reused_from"]["git_commit"] == "abc1234"
    with pytest.raises(ValueError, match="protocol"):
        reused_rows([rec], {**protocol, "test_seed": 1})


def test_load_results_refuses_a_record_named_unlike_its_file(tmp_path):
    """A second record named ``payoff`` in ``ppo_case33bw.json`` once replaced ``payoff.json`` in the report."""
    from anm_torchrl.experiments.io import load_results, result, write_json

    write_json(tmp_path / "payoff.json", result("payoff", "ok", {"x": 1}))
    write_json(tmp_path / "bench.json", {"rows": []})  # not a result record: skipped
    assert set(load_results(tmp_path)) == {"payoff"}
    write_json(tmp_path / "ppo_case33bw.json", result("payoff", "ok", {"x": 2}))
    with pytest.raises(ValueError, match="ppo_case33bw.json.*not the file stem"):
        load_results(tmp_path)
    (tmp_path / "ppo_case33bw.json").write_text("{truncated")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_results(tmp_path)


def test_portable_paths_drop_the_machines_top_level_folder():
    """A run directory directly under /tmp once rendered as '.../tmp/<run>' in docs/RESULTS.md."""
    from anm_torchrl.experiments.formatting import portable, portable_command

    assert portable("/tmp/repro10_run1") == ".../repro10_run1"
    assert portable("/tmp/repro/tr_full") == ".../repro/tr_full"
    assert portable("/tmp") == "..."
    assert "/tmp" not in portable_command("reproduce.py out_dir=/tmp/run1 publish=true")


def test_every_experiment_has_the_one_signature():
    """The registry is what reproduce.py loops over: every entry is ``run(cfg, ctx)``, every preset names only
    registered experiments, and an unknown name is refused with the list of known ones."""
    import inspect

    from omegaconf import OmegaConf

    from anm_torchrl.experiments import registry

    for name, entry in registry.EXPERIMENTS.items():
        assert list(inspect.signature(entry.run).parameters) == ["cfg", "ctx"], name
    for preset in sorted((REPO / "recipes" / "conf" / "preset").glob("*.yaml")):
        names = OmegaConf.load(preset).get("experiments", [])
        assert set(names) <= set(registry.EXPERIMENTS), (preset.name, names)
    with pytest.raises(ValueError, match="unknown experiment 'nope'.*pinn_losses"):
        registry.get("nope")
