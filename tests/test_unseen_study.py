"""The study of networks nobody tuned (anm_torchrl.experiments.unseen): a random network written as a user's file,
its optimum and do-nothing on the recipes' test states, a recipe's documented command on it, reuse on a second run."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from anm_torchrl.experiments import cells, unseen
from tests.test_recipes_ppo import TINY

SPEC = "101:6:radial"
# PPO's smoke budget, with 2 test states of 8 steps (the optimum's horizon) instead of the feeders' 4 x 3,000
SMOKE = tuple(k for k in TINY if not k.startswith(("logger.progress=", "eval.test_episodes="))) + (
    "eval.test_episodes=2", "eval.test_max_steps=8")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    runs = tmp_path_factory.mktemp("unseen") / "runs"
    return unseen.study([SPEC], ["ppo"], [0], runs, jobs=1, overrides=SMOKE), runs.resolve()


def test_a_study_scores_the_recipe_against_the_optimum_on_the_same_states(study):
    record, runs = study
    assert record["failed"] == [] and record["overrides"] == list(SMOKE)
    (net,) = record["networks"]
    assert (runs / net["file"]).is_file() and net["n_bus"] == 6 and net["topology"] == "radial"
    assert net["protocol"] == {"episodes": 2, "seed": 0, "steps": 8, "gamma": 0.995}
    # the optimum plans the same 8 steps do-nothing runs: it cannot do worse (IPOPT's tolerance aside)
    assert net["optimum"] >= net["do_nothing"] - 1e-6
    (ppo,) = net["algorithms"]
    assert ppo["command"].startswith(f"python recipes/ppo.py network={net['file']} seed=0")
    (run,) = ppo["runs"]
    assert run["frames"] == 64 and run["discounted_return"] == ppo["discounted_return"]
    gain = 100 * (run["discounted_return"] - net["do_nothing"]) / (net["optimum"] - net["do_nothing"])
    assert ppo["gain_pct"] == pytest.approx(gain)
    table = unseen.markdown(record)
    assert f"| `{SPEC}` | 6 |" in table and "64 frames" in table


def test_a_second_run_reuses_the_baselines_and_the_cells(study, monkeypatch):
    record, runs = study
    monkeypatch.setattr(cells, "ProcessPoolExecutor", lambda *a, **k: pytest.fail("a finished cell was run again"))
    monkeypatch.setattr(unseen, "ProcessPoolExecutor", lambda *a, **k: pytest.fail("the baselines were solved again"))
    again = unseen.study([SPEC], ["ppo"], [0], runs, jobs=1, overrides=SMOKE)
    assert again["networks"] == record["networks"]


def test_a_cell_trained_on_other_network_data_is_trained_again(study, tmp_path):
    """The same file name with other tables (the generator changed): its network key differs, the cell is not
    reused."""
    record, runs = study
    cell = tmp_path / "cell"
    shutil.copytree(runs / f"{record['networks'][0]['file'][:-4]}_ppo_s0", cell)
    marker = json.loads((cell / "study_cell.json").read_text())
    command = [f"hydra.run.dir={cell}" if a.startswith("hydra.run.dir=") else a for a in marker["command"]]
    assert marker["network_key"] == record["networks"][0]["network_key"]
    (cell / "study_cell.json").write_text(json.dumps({**marker, "command": command}))
    assert cells.finished(command, cell)
    (cell / "study_cell.json").write_text(json.dumps({**marker, "command": command, "network_key": "other"}))
    assert not cells.finished(command, cell)


def test_baselines_of_another_network_or_protocol_are_not_reused(study):
    record, runs = study
    net = record["networks"][0]
    path, gap = runs / net["file"], (runs / net["file"]).with_suffix(".gap.json")
    protocol, key = net["protocol"], net["network_key"]
    assert unseen._baselines_done(gap, path, protocol, key)
    assert not unseen._baselines_done(gap, path, protocol, "another key")
    assert not unseen._baselines_done(gap, path, {**protocol, "steps": 9}, key)


def test_a_kept_record_keeps_its_baselines_and_the_columns_not_re_made(study, tmp_path, monkeypatch):
    """``keep``: one column re-made after its defaults change, the optimum not solved again (no gap file here), the
    other columns and their order kept and marked; a kept row of another network is refused by name."""
    record, _ = study
    keep = json.loads(json.dumps(record))
    keep["algorithms"] = ["sac", "ppo"]
    sac = {**keep["networks"][0]["algorithms"][0], "algorithm": "sac", "discounted_return": 0.25}
    keep["networks"][0]["algorithms"].insert(0, sac)
    monkeypatch.setattr(unseen, "ProcessPoolExecutor", lambda *a, **k: pytest.fail("the baselines were solved again"))
    again = unseen.study([SPEC], [], [0], tmp_path / "runs", jobs=1, overrides=SMOKE, keep=keep, keep_source="k.json")
    (net,) = again["networks"]
    assert again["algorithms"] == ["sac", "ppo"] and again["kept_from"] == "k.json"
    first = record["networks"][0]
    assert (net["optimum"], net["do_nothing"]) == (first["optimum"], first["do_nothing"])
    assert net["baselines_kept_from"] == "k.json"
    assert [a["algorithm"] for a in net["algorithms"]] == ["sac", "ppo"]
    assert net["algorithms"][0]["discounted_return"] == 0.25
    assert all(a["kept_from"] == "k.json" for a in net["algorithms"])
    assert "| SAC | PPO |" in unseen.markdown(again)
    keep["networks"][0]["network_key"] = "another"
    with pytest.raises(ValueError, match=f"k.json: {SPEC} there is network another"):
        unseen.study([SPEC], [], [0], tmp_path / "runs", jobs=1, overrides=SMOKE, keep=keep, keep_source="k.json")
    with pytest.raises(ValueError, match="not a record of this study"):
        unseen.study([SPEC], [], [0], tmp_path / "runs", jobs=1, overrides=SMOKE, keep=[], keep_source="k.json")


def test_a_malformed_spec_is_refused_by_name(capsys):
    from anm_torchrl.cli import unseen_networks as cli

    with pytest.raises(ValueError, match=r"network spec '9101:18': expected SEED:BUSES:radial\|meshed"):
        unseen.parse_spec("9101:18")
    with pytest.raises(SystemExit):
        cli.main(["--networks", "9101:18:ring"])
    assert "network spec '9101:18:ring': expected SEED:BUSES:radial|meshed" in capsys.readouterr().err


def test_a_network_file_is_a_spec(tmp_path):
    """A user's file (e.g. a SimBench grid from ``python -m anm_torchrl.cli.import_network``) takes a random spec's
    place: copied beside the runs, described from its own tables; a missing one is refused by name."""
    from anm_torchrl.networks.random import generate
    from anm_torchrl.networks.user import save_network

    case = generate(7, n_bus=6, meshed=False)
    src = save_network(tmp_path / "mine.npz", case.network, case.load_p, case.gen_p_max)
    path, meta = unseen.write_network(str(src), tmp_path / "runs")
    assert path == tmp_path / "runs" / "mine.npz" and path.read_bytes() == src.read_bytes()
    kinds = np.asarray(case.network["device"], dtype=float)[:, 2]
    assert (meta["n_bus"], meta["n_storage"], meta["topology"]) == (6, int((kinds == 3).sum()), "file")
    assert meta["network_key"] and meta["n_load"] == int((kinds == -1).sum())
    with pytest.raises(ValueError, match=r"network spec '.*gone.npz': no such network file"):
        unseen.parse_spec(str(tmp_path / "gone.npz"))


def test_the_committed_record_matches_its_block():
    from tests.test_recipes_ppo import ROOT

    path = ROOT / "results" / "unseen" / "unseen_networks.json"
    if not path.is_file():
        pytest.skip("no study record committed yet")
    record = json.loads(path.read_text())
    text = (ROOT / "README.md").read_text()
    start = text.index(unseen.MARKERS[0]) + len(unseen.MARKERS[0]) + 1
    block = text[start:text.index(unseen.MARKERS[1])]
    assert block == unseen.markdown(record) + "\n_From `results/unseen/unseen_networks.json`._\n"
