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
EXPERIMENTS = ["pinn_losses", "speed", "accuracy", "rollout_error", "adaptability", "sweep", "ppo_curves"]


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reproduce")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ANM_TORCHRL_HOME": str(out / "home")}
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), "preset=tiny", f"out_dir={out}",
                           f"results_md={out / 'RESULTS.md'}"], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
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
    assert (results / "speed_table.csv").exists() and (results / "figures" / "fig6_speed.png").exists()


def test_results_md_is_generated(results: Path):
    md = (results / "RESULTS.md").read_text()
    assert "do not edit by hand" in md and md.count("| **") >= 4
    for title in ("Fig. 5", "Fig. 6", "Fig. 7", "Figs. 8–9", "Figs. 10–11", "PPO training curves"):
        assert title in md


def test_report_only_rewrites_the_page_from_the_records(results: Path):
    """``report_only=true`` runs nothing: same records, a page rendered again from them."""
    md = results / "RESULTS_again.md"  # beside the original, so figure links compare equal
    records = {p.name: p.read_bytes() for p in results.glob("*.json")}
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "reproduce.py"), f"out_dir={results}",
                           f"results_md={md}", "report_only=true"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    assert records == {p.name: p.read_bytes() for p in results.glob("*.json")}
    assert md.read_text().split("\n", 3)[3] == (results / "RESULTS.md").read_text().split("\n", 3)[3]


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


def test_run_ppo_starts_from_an_empty_run_dir(tmp_path: Path, monkeypatch):
    """Logs left by an earlier run of the same cell are not read back as part of the new run's curve."""
    from anm_torchrl.experiments import ppo_runs

    stale = tmp_path / "cell"
    (stale / "logs").mkdir(parents=True)
    (stale / "summary.json").write_text("{}")
    seen = {}

    def fake_run(cmd, **kw):
        seen["existed"] = stale.exists()
        return subprocess.CompletedProcess(cmd, 1, "", "boom")

    monkeypatch.setattr(ppo_runs.subprocess, "run", fake_run)
    rec = ppo_runs.run_ppo(["surrogate=none"], stale)
    assert seen["existed"] is False and rec["summary"] is None and rec["curve"] == []
    assert rec["error"].startswith("exit 1") and not rec["ok"]
