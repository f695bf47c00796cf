"""README's result tables, rendered from the committed records (``results/<study>/*.json``), never typed by hand.

README.md marks each generated block with a pair of HTML comments::

    <!-- results:claims -->
    ...generated...
    <!-- /results:claims -->

:func:`update_readme` rewrites every marked block from the records (``reproduce.py publish=true`` calls it), and
the tests check that the committed README equals what the committed records render (:func:`render_readme`).
Each block ends with the record, preset and git commit it comes from.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from anm_torchrl.experiments.payoff_report import readme_pinn_accuracy
from anm_torchrl.experiments.registry import EXPERIMENTS
from anm_torchrl.experiments.claims import CLAIMS
from anm_torchrl.experiments.formatting import md_table, portable_command

BLOCK = re.compile(r"(<!-- results:(?P<name>[a-z_]+) -->\n)(?P<body>.*?)(<!-- /results:(?P=name) -->)", re.S)


def _source(rec: dict | None, run: dict | None, records_dir: str | None = None) -> str:
    """Where a block's numbers come from: record file, preset, date and git commit."""
    if not rec:
        return "_(no record)_"
    meta = rec.get("meta", {})
    commit = (meta.get("versions") or {}).get("git_commit") or "unknown"
    preset, date = (run or {}).get("preset"), (run or {}).get("date")
    for u in (run or {}).get("updates", []):  # the last update that re-ran this experiment made its record
        if rec["name"] in u.get("experiments", {}):
            preset, date = u.get("preset") or preset, u.get("date") or date
    when = f", run on {str(date)[:10]}" if date else ""
    study = EXPERIMENTS[rec["name"]].study if rec["name"] in EXPERIMENTS else "reproduction"
    where = records_dir or f"results/{study}"  # a run directory's page names its own records
    return f"_From `{where}/{rec['name']}.json` (preset `{preset}`, git commit `{commit[:7]}`{when})._"


def block_claims(res: dict[str, Any]) -> str:
    rows = []
    for text, fn in CLAIMS:
        what, verdict = fn(res)
        rows.append({"claim (paper)": text, "verdict here": f"**{verdict}**", "measured": what})
    sources = " ".join(_source(res.get(n), res.get("run"), res.get("records_dir"))
                       for n in ("speed", "ppo_curves", "sweep") if res.get(n))
    return md_table(rows, ["claim (paper)", "verdict here", "measured"]) + "\n\n" + sources + _reused_curves(res)


def _reused_curves(res: dict[str, Any]) -> str:
    """The ppo_curves envs whose runs an earlier run of the experiment measured (same states), with its commit."""
    rec = res.get("ppo_curves") or {}
    reused = {lab: runs[0]["reused_from"] for lab, runs in ((rec.get("data") or {}).get("runs") or {}).items()
              if runs and runs[0].get("reused_from")}
    if not reused:
        return ""
    by_commit: dict[str, list[str]] = {}
    for lab, origin in reused.items():
        by_commit.setdefault(str(origin.get("git_commit"))[:7], []).append(f"`{lab}`")
    return (" _PPO runs of " + "; ".join(f"{', '.join(labs)} from git commit `{c}`" for c, labs in by_commit.items())
            + " (an earlier run of `ppo_curves` on the same states, merged into this record)._")


def block_test_returns(res: dict[str, Any]) -> str:
    rec = res.get("test_returns")
    if not rec or rec["status"] not in ("ok", "partial"):
        return "_(test_returns not measured)_"
    d = rec["data"]
    rows = [{**r, "policy": r["policy"] if not r.get("trained_on") else f"{r['policy']} (trained on "
             f"`{r['trained_on']}`)"} for r in d["rows"]]
    pr = d["protocol"]
    head = (f"{pr['test_episodes']} test states (seed {pr['test_seed']}), T = {pr['max_steps']:,}, "
            f"γ = {pr['gamma']}; PPO `best` = the checkpoint chosen on the validation states, mean ± std over seeds:")
    table = md_table(rows, ["policy", "seeds", "discounted_return", "discounted_return_std", "return", "frames",
                          "seconds"], {"discounted_return": ".2f", "discounted_return_std": ".2f", "return": ".1f",
                                       "frames": ",.0f", "seconds": ".0f"})
    reused = sorted({str(r["reused_from"].get("git_commit"))[:7] for r in d["rows"] if r.get("reused_from")})
    if reused:
        table += (f"\n\nRows measured by earlier runs of this experiment on the same states and protocol (git "
                  f"commit {', '.join(f'`{c}`' for c in reused)}) and merged into this record.")
    na = "; ".join(f"`{k}`: {portable_command(v)[:120]}" for k, v in d.get("not_available", {}).items())
    return (f"{head}\n\n{table}\n\n" + (f"Not available: {na}\n\n" if na else "")
            + _source(rec, res.get("run"), res.get("records_dir")))


def block_adaptability(res: dict[str, Any]) -> str:
    rec = res.get("adaptability")
    if not rec or rec["status"] not in ("ok", "partial"):
        return "_(adaptability not measured)_"
    rows = rec["data"]["rows"]
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    table = []
    for agent in dict.fromkeys(r["agent"] for r in rows):
        for lab in dict.fromkeys(r["surrogate"] for r in rows if r["agent"] == agent):
            row = {"agent": agent, "surrogate": lab}
            row.update({sc: next((r["one_step_mae"] for r in rows if (r["agent"], r["surrogate"], r["scenario"]) ==
                                  (agent, lab, sc)), None) for sc in scenarios})
            table.append(row)
    na = rec["data"].get("not_available") or {}
    missing = (f"Not in this record (no trained model when it ran): {', '.join(f'`{k}`' for k in na)}.\n\n"
               if na else "")
    return ("One-step (teacher-forced) state MAE along the episodes of each scenario (MW, MVAr, MWh):\n\n"
            + md_table(table, ["agent", "surrogate", *scenarios]) + "\n\n" + missing
            + _source(rec, res.get("run"), res.get("records_dir")))


BLOCKS = {"claims": block_claims, "test_returns": block_test_returns, "adaptability": block_adaptability,
          "pinn_accuracy": readme_pinn_accuracy}


def render_readme(text: str, res: dict[str, Any]) -> str:
    """``text`` with every marked block replaced by its rendering from the records ``res`` (name -> record)."""
    def one(m: re.Match) -> str:
        name = m.group("name")
        if name not in BLOCKS:
            raise ValueError(f"README block <!-- results:{name} -->: unknown; known blocks {sorted(BLOCKS)}")
        return m.group(1) + BLOCKS[name](res).rstrip() + "\n" + m.group(4)

    return BLOCK.sub(one, text)


def update_readme(path: str | Path, res: dict[str, Any]) -> Path:
    """Rewrite README's marked blocks at ``path`` from the records ``res``."""
    path = Path(path)
    path.write_text(render_readme(path.read_text(), res))
    return path
