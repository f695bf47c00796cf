"""The published gap tables: losses and gains against the optimum, PPO rows from records of the same states, and
the README / docs blocks rendered from the committed records."""

import copy
import json
from pathlib import Path

import pytest

from anm_torchrl.experiments import gap, gap_table
from anm_torchrl.experiments.records import current_path

REPO = Path(__file__).resolve().parents[1]
TABLES = sorted((REPO / "results" / "gap").glob("optimal_gap_table*.json"))


def test_table_compares_rows_on_the_states_they_cover():
    rows = {"optimal": {"discounted_return": [-2.0, -4.0, -6.0]},
            "a": {"discounted_return": [-4.0, -8.0, -12.0]},
            "b": {"discounted_return": [-3.0], "episode_index": [1]}}
    t = {r["policy"]: r for r in gap.table(rows, 3)}
    assert t["a"]["loss_pct_of_optimum"] == pytest.approx(200.0)
    assert t["b"]["loss_pct_of_optimum"] == pytest.approx(75.0)  # against the optimum's -4 on state 1 only
    assert t["optimal"]["loss_pct_of_optimum"] == pytest.approx(100.0)
    rows["optimal"]["discounted_return"] = [0.1, 0.2, 0.3]  # a gain: there is no loss to compare with
    assert gap.table(rows, 3)[0]["loss_pct_of_optimum"] is None


def _rec(opt, dn, mpc, network="case33bw"):
    pr = {"network": network, "episodes": len(opt), "seed": 0, "steps": 3000, "gamma": 0.995}
    return {"protocol": pr, "rows": {"optimal": {"discounted_return": opt}, "do_nothing": {"discounted_return": dn},
                                     "mpc_16": {"discounted_return": mpc}}}


def _ppo(dn_mean, vals, network="case33bw", **proto):
    dn = {"discounted_return": dn_mean, "episodes": 2, "test_seed": 0, "max_steps": 3000, "gamma": 0.995, **proto}
    return {"meta": {"versions": {"git_commit": "abc1234"}},
            "data": {"ppo": {"network": network, "test_baselines": {"do_nothing": dn},
                             "table": [{"env": "none", "seeds": [0, 1], "frames": [10, 20],
                                        "test_best_discounted_return": vals}]}}}


def test_gain_is_defined_where_the_optimum_earns():
    """case33bw's returns are positive: no loss ratio, but the share of the optimum's gain over do-nothing."""
    rec = gap_table.combine(_rec([0.2, 0.4], [-0.1, -0.1], [0.1, 0.1]), ppo=_ppo(-0.1, [0.0, 0.2]))
    by = {r["row"]: r for r in rec["rows"]}
    assert by["mpc_16"]["loss_pct_of_optimum"] is None
    assert by["mpc_16"]["gain_pct_of_optimum"] == pytest.approx(100 * 0.2 / 0.4)
    assert by["optimal"]["gain_pct_of_optimum"] == pytest.approx(100.0)
    assert by["do_nothing"]["gain_pct_of_optimum"] == pytest.approx(0.0)
    ppo = by["ppo_best_none"]  # mean 0.1 over seeds, sample std 0.1414
    assert ppo["gain_pct_of_optimum"] == pytest.approx(50.0) and ppo["seeds"] == 2
    assert ppo["gain_pct_std"] == pytest.approx(100 * 0.1414213562 / 0.4)
    body = gap_table.render_block(rec)
    assert "loss, %" not in body and "| 50.0 % ± 35.4 |" in body


def test_ppo_rows_must_come_from_the_same_states():
    rec = _rec([0.2, 0.4], [-0.1, -0.1], [0.1, 0.1])
    with pytest.raises(ValueError, match="not measured on the same states"):
        gap_table.combine(rec, ppo=_ppo(-0.1 * (1 + 1e-6), [0.0, 0.2]))
    with pytest.raises(ValueError, match="test protocol"):
        gap_table.combine(rec, ppo=_ppo(-0.1, [0.0, 0.2], test_seed=1))
    with pytest.raises(ValueError, match="test protocol"):
        gap_table.combine(rec, ppo=_ppo(-0.1, [0.0, 0.2], network="cigre_mv"))
    with pytest.raises(ValueError, match="lacks a test return"):
        gap_table.combine(rec, ppo=_ppo(-0.1, [0.0, None]))
    no_dn = copy.deepcopy(rec)
    del no_dn["rows"]["do_nothing"]
    with pytest.raises(ValueError, match="do_nothing row"):
        gap_table.combine(no_dn, ppo=_ppo(-0.1, [0.0, 0.2]))


def test_each_network_has_its_own_block():
    assert gap_table.readme_block("anm6_easy").pattern == gap_table.README_BLOCK.pattern
    text = "<!-- optimum:gap -->\nA\n<!-- /optimum:gap -->\n<!-- optimum:gap:case33bw -->\nB\n<!-- /optimum:gap:case33bw -->"
    assert gap_table.readme_block("case33bw").search(text).group(2) == "B\n"
    assert gap_table.readme_block("cigre_mv").search(text) is None


@pytest.mark.parametrize("path", TABLES, ids=[p.name for p in TABLES])
def test_gap_blocks_are_rendered_from_the_records(path):
    """Each network's gap table in README / docs/OPTIMAL.md is its committed record's rendering, and the record's
    own rows are what its committed gap record gives."""
    rec = json.loads(path.read_text())
    src = json.loads((REPO / current_path(rec["command"].split("--combine ")[1].split()[0])).read_text())
    mine = [r for r in rec["rows"] if r["source"] == "gap"]
    assert mine == [r for r in gap_table.combine(src, record=rec["record"])["rows"] if r["source"] == "gap"]
    body = gap_table.render_block(rec)
    block = gap_table.readme_block(gap_table.network_of(rec["protocol"]))
    pages = [p for p in ("README.md", "docs/OPTIMAL.md") if f" {p}" in rec["command"].split("--readme")[1]]
    assert "docs/OPTIMAL.md" in pages
    for page in pages:
        m = block.search((REPO / page).read_text())
        assert m is not None and m.group(2) == body, page


def test_results_page_holds_every_gap_table():
    """docs/RESULTS.md's section is what the generator renders from the committed tables (so a regenerated page
    keeps it, and every network's table is on it)."""
    from anm_torchrl.experiments.report import optimum_section

    tables = {p.stem: json.loads(p.read_text()) for p in TABLES}
    assert tables, "no results/gap/optimal_gap_table*.json"
    assert optimum_section(tables) in (REPO / "docs" / "RESULTS.md").read_text()


def test_a_page_without_the_block_refuses_the_table(tmp_path):
    rec = gap_table.combine(_rec([0.2, 0.4], [-0.1, -0.1], [0.1, 0.1]))
    good, bad = tmp_path / "good.md", tmp_path / "bad.md"
    good.write_text("<!-- optimum:gap:case33bw -->\nold\n<!-- /optimum:gap:case33bw -->\n")
    bad.write_text("no block here\n")
    with pytest.raises(ValueError, match="bad.md: no <!-- optimum:gap:case33bw -->"):
        gap_table.update_pages([good, bad], rec)
    assert "old" in good.read_text()  # nothing written when one page lacks the block
    gap_table.update_pages([good], rec)
    assert gap_table.render_block(rec) in good.read_text()


def test_cli_render_rewrites_only_the_gap_block(tmp_path):
    """``python -m anm_torchrl.cli.gap --render <table> --readme <pages>`` rewrites a page's block from the committed
    table (no evaluation, no record written): a stale block is replaced, the rest of the page kept."""
    from anm_torchrl.cli import gap as cli

    rec_path = REPO / "results" / "gap" / "optimal_gap_table.json"
    start, end = gap_table.block_markers(gap_table.ANM6)
    page = tmp_path / "page.md"
    page.write_text(f"before\n{start}\nstale\n{end}\nafter\n")
    before = {p: p.read_bytes() for p in (REPO / "results" / "gap").glob("*.json")}
    assert cli.main(["--render", str(rec_path), "--readme", str(page)]) == {}
    body = gap_table.render_block(json.loads(rec_path.read_text()))
    assert page.read_text() == f"before\n{start}\n{body}{end}\nafter\n"
    assert before == {p: p.read_bytes() for p in (REPO / "results" / "gap").glob("*.json")}
    with pytest.raises(SystemExit):
        cli.main(["--render", str(rec_path)])  # no page to render into
    with pytest.raises(SystemExit):
        cli.main(["--rows", "do_nothing"])  # a measurement needs --out
