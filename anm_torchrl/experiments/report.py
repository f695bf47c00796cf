"""``docs/RESULTS.md``, generated from the result records: every table, figure and verdict comes from
``results/<study>/*.json`` (nothing is typed by hand). Redraw with ``python recipes/reproduce.py report_only=true
publish=true``; regenerate the records with ``python recipes/reproduce.py preset=full publish=true``.
"""

from __future__ import annotations

import os
from pathlib import Path

from anm_torchrl.experiments.claims import CLAIMS, load_note
from anm_torchrl.experiments.formatting import fmt, md_table, portable, portable_command

TEMPLATE = """# Results: reproducing the paper's experiments on anm_torchrl

_Generated from the records by `python recipes/reproduce.py`; do not edit by hand (`report_only=true` redraws it,
running nothing). Which run made each record: the table below; every run with its command, date and git commit:
`run.json` (`updates`) beside the records; the command and claim of every committed record: `results/INDEX.json`._
_First run `{command}` on {date}{updates}._
Preset **{preset}**, total wall time {wall:.0f} s, seeds {seeds}.

**Machine.** {machine}
**Versions.** {versions}

Which run produced each record (records under `{records_where}`; PPO learning curves are evaluated after every update on
the fixed states named in their section, the `test_returns` figures on the held-out test states):

{provenance}

## The four claims

| claim (paper) | measured here | verdict |
|---|---|---|
{claims_table}

{sections}
"""


def _status(rec: dict | None) -> str:
    if not rec:
        return "**not run** (not selected in this preset)"
    if rec["status"] in ("not available", "error"):
        return f"**{rec['status']}**: {portable_command(rec.get('reason'))}"
    na = rec.get("data", {}).get("not_available") or {}
    extra = ("; not available: " + "; ".join(f"`{k}` ({portable_command(v)[:160]})" for k, v in na.items())
             if na else "")
    return f"status **{rec['status']}**{extra}"


def _fig(figs: dict, name: str, rel_to: Path) -> str:
    p = figs.get(name)
    if not p:
        return f"_(figure `{name}`: no data)_"
    return f"![{name}]({os.path.relpath(p, rel_to)})"


# --------------------------------------------------------------------------------------------- sections
def sections(res: dict, figs: dict, rel: Path, machine: str) -> str:
    out = []
    rec = res.get("pinn_losses")
    out.append(f"""## Fig. 5 — PINN loss components

**Paper.** The generator KKT, storage KKT and power-balance losses decrease over training.
**Measured** on {machine}: {_status(rec)}. {("Read from the PINN training's TensorBoard run (" + portable(rec['data']['log_dir']) + "); final values: " + ", ".join(
        f"`{k}` {v[-1][1]:.3g}" for k, v in sorted(rec['data']['scalars'].items()) if k.endswith('/loss'))) if rec and rec['status'] == 'ok' else ''}

{_fig(figs, 'fig5_pinn_losses', rel)}
""")
    rec = res.get("speed")
    table = md_table(rec["data"]["table"], ["impl", "mode", "batch", "median", "q25", "q75", "speedup_vs_gym_anm"]) \
        if rec and rec["status"] in ("ok", "partial") else ""
    out.append(f"""## Fig. 6 — inference time per transition (the honest speed table)

**Paper.** PINN median 0.0021 s vs 0.0194 s for the plain env over 1,000 transitions (≈10×).
**Measured** on {machine}, same run, seconds per transition: {_status(rec)}. `gym_anm` is gym-anm 2.0.1 itself;
`anm6env` the batched true simulator on its default CPU backend (the compiled numba loop), `anm6env_torch` the
same env on its batched-torch backend, `grid_sim` the raw physics without TorchRL; every other row is a surrogate
env. Batch-1 times are dominated by per-call overhead (TorchRL's `step_and_maybe_reset`, model dispatch).
{load_note(rec)}
{table}

{_fig(figs, 'fig6_speed', rel)} {_fig(figs, 'fig6b_speed_scaling', rel)}
""")
    rec = res.get("accuracy")
    table = ""
    if rec and rec["status"] in ("ok", "partial"):
        table = md_table(rec["data"]["rows"], ["model", "train_dataset", "eval_dataset", "split", "r2", "mae"])
    out.append(f"""## Fig. 7 — R² and MAE of the data-driven surrogates, in- and cross-dataset

**Paper.** Agent-based data beat generative data; XGB has the best R²/MAE, barely ahead of the PINN.
**Measured** (metrics written by the data-driven training recipe): {_status(rec)}.

{table}

{_fig(figs, 'fig7_accuracy', rel)}
""")
    rec = res.get("rollout_error")
    table = ""
    if rec and rec["status"] in ("ok", "partial"):
        rows = []
        for agent, a in rec["data"]["agents"].items():
            for lab, r in a["surrogates"].items():
                rows.append({"agent": agent, "policy": a["policy"], "surrogate": lab, "one-step MAE": r["one_step"]["mae"],
                             "free-running MAE": (r.get("free_running") or {}).get("mae")})
        table = md_table(rows, ["agent", "policy", "surrogate", "one-step MAE", "free-running MAE"])
    out.append(f"""## Figs. 8–9 — surrogate error along expert and random episodes; free-running rollouts

**Paper.** The PINN has the lowest one-step MAE along expert- and random-agent episodes, even where others have
higher R²; its error over an expert episode shows daily periodicity.
**Measured** ({(rec or {}).get('data', {}).get('episodes')} episodes × {(rec or {}).get('data', {}).get('steps')} steps,
`none` = the true simulator checked against itself, 0 by construction): {_status(rec)}.

{table}

{_fig(figs, 'fig8_one_step_mae', rel)} {_fig(figs, 'fig9_episode_mae', rel)}
{_fig(figs, 'fig8b_free_running_mae', rel)} {_fig(figs, 'fig9b_free_running_curve', rel)}
""")
    rec = res.get("sweep")
    table = ""
    if rec and rec["status"] in ("ok", "partial"):
        table = md_table(rec["data"]["grid"], ["n_envs", "buffer", "frames_per_batch", "seeds", "mean_return",
                                             "mean_return_std", "train_time_s",
                                             "frames", "evaluations"]) + "\n\nCorrelations: " + ", ".join(
            f"{a}–{b} {fmt(rec['data']['correlation'][a][b], '.2f')}" for a, b in
            (("buffer", "mean_return"), ("n_envs", "mean_return"), ("buffer", "train_time_s"),
             ("n_envs", "train_time_s"))) + f".\n\nMultirun form: `{rec['data']['command']}`"
    out.append(f"""## Figs. 10–11 — structural sweep n_envs × buffer (PPO on the PINN surrogate)

**Paper.** Best: 100 envs, buffer 30; return correlates negatively with buffer size (more than with n_envs);
training time grows with both.
**Measured:** {_status(rec)}.

{table}

{_fig(figs, 'fig10_11_sweep', rel)}
""")
    rec = res.get("ppo_curves")
    table = ""
    if rec and rec["status"] in ("ok", "partial"):
        table = md_table(rec["data"]["table"], ["env", "seeds", "last_mean_return", "last_mean_return_std",
                                              "best_return", "wall_s", "train_s", "frames", "threshold_reached",
                                              "threshold_runs", "threshold_wall_s", "threshold_wall_s_mean",
                                              "surrogate_train_s", "threshold_wall_with_training_s",
                                              "threshold_frames"])
        bl = [{"baseline": k, **v} for k, v in rec["data"]["baselines"].items()]
        table += "\n\nBaselines on the same evaluation states:\n\n" + md_table(
            bl, ["baseline", "available", "return", "discounted_return", "reason"])
        reused = {lab: r[0]["reused_from"] for lab, r in rec["data"]["runs"].items() if r and r[0].get("reused_from")}
        if reused:
            table += "\n\nRuns reused from an earlier record (same states and threshold, not trained again): " \
                + ", ".join(f"`{lab}` (git commit `{str(o.get('git_commit'))[:7]}`)" for lab, o in reused.items()) + "."
        loads = [x for runs in rec["data"]["runs"].values() for r in runs for x in (r.get("load_avg_1min") or [])]
        if loads:  # the times below are wall times: other processes on the machine stretch them
            table += (f"\n\n1-minute load average before / after each PPO run: {min(loads):.1f}–{max(loads):.1f} "
                      f"({rec['meta'].get('machine', {}).get('logical_cores')} logical cores).")
        seed = (rec["meta"].get("config") or {}).get("base", {}).get("eval.seed")
        table += (f"\n\nThreshold for 'time to reach': return ≥ {fmt(rec['data']['threshold'])} on the evaluation "
                  f"states (`eval.seed={seed}`). `threshold_wall_s` is the Kaplan–Meier median over seeds of the PPO wall time "
                  "(collection, updates, evaluations) to the first evaluation at or above it, a run that never reaches it counted "
                  "as censored at its run length (empty when fewer than half reached it); `_mean` is the mean of "
                  "those times, a lower bound when a run is censored; `with_training` adds the surrogate's "
                  "training time (`surrogate_train_s`: CPU seconds of the PINN's training in this reproduction, one "
                  "thread, i.e. its wall time on an idle machine; a loaded machine stretches wall time).")
    out.append(f"""## PPO training curves (paper Fig. 12 and training time)

**Paper.** PPO on the PINN surrogate reaches a score comparable to PPO on the original env in ≈50 % less time;
policies trained on data-driven surrogates fail on the real env.
**Measured** (evaluation on the true simulator after every update): {_status(rec)}.

{table}

{_fig(figs, 'fig12_ppo_curves', rel)}
""")
    rec = res.get("test_returns")
    from anm_torchrl.experiments.readme_blocks import block_test_returns

    out.append(f"""## Returns on the held-out test states (PPO and baselines)

**Protocol.** PPO's best checkpoint is chosen on the validation states; every figure here is on separate test
states, the baselines on the same ones: {_status(rec)}.

{block_test_returns(res) if rec and rec["status"] in ("ok", "partial") else ""}
""")
    rec = res.get("adaptability")
    table = md_table(rec["data"]["rows"], ["scenario", "shift", "agent", "surrogate", "one_step_mae"]) \
        if rec and rec["status"] in ("ok", "partial") else ""
    out.append(f"""## Beyond the paper — changed demand / generation profiles without retraining

**Question.** Does each surrogate stay accurate when the load or renewable series change (scaled, or shifted in
time)? Every surrogate env runs on the changed simulator and every model reads its series from it; the PINN's
physics sees them, the data-driven models only what their training data covered.
**Measured:** {_status(rec)}.

{table}

{_fig(figs, 'adaptability', rel)}
""")
    out.append(payoff_section(res.get("payoff")))
    out.append(optimum_section(res.get("optimal_gap_tables")))
    return "\n".join(out)


def payoff_section(rec: dict | None) -> str:
    """Issue 13's study "when does a surrogate pay off?": its tables and its cost/accuracy findings, generated from
    ``results/payoff/payoff.json`` (:func:`anm_torchrl.experiments.payoff_report.markdown` and ``cost_verdict``)."""
    from anm_torchrl.experiments import payoff_report

    m = (rec or {}).get("meta", {}).get("machine")
    machine = _machine(m) if m else "not recorded"
    body = (f"{payoff_report.markdown(rec)}\n\n**Cost and accuracy, read from the record.** "
            f"{payoff_report.cost_verdict(rec)}") if rec and rec.get("data") else ""
    return f"""<!-- payoff:begin (generated by anm_torchrl.experiments.report.payoff_section from results/payoff/payoff.json) -->
## When does a surrogate pay off? (issue 13, item 5)

Record: `results/payoff/payoff.json` (`python recipes/reproduce.py preset=payoff`; the exact command, the surrogate models
used and how they were trained are in its `meta.notes`): {_status(rec)}. Machine: {machine}, shared with other jobs:
every timing carries the 1-min load average read before it (L…); compare the ratios (× numba, measured next to each
other in the same run), not absolute µs. Warm-up (construction, model load, first reset and step) is timed apart
(`warm_s` in the record). gym-anm's generic env runs batch 1 only. A batched row predicted (from the next smaller
batch) to need > 30 s per step is "skipped"; "n/a": no trained model for that network.

{body}
<!-- payoff:end -->
"""


def optimum_section(tables: dict[str, dict] | None) -> str:
    """Issue 15's gap tables, one per network, from the committed ``results/gap/optimal_gap_table*.json`` (file stem ->
    record): each is :func:`anm_torchrl.experiments.gap_table.render_block` inside the network's own block markers, the
    ones ``python -m anm_torchrl.cli.gap --combine ... --readme docs/RESULTS.md`` rewrites in place."""
    from anm_torchrl.experiments import gap_table

    blocks = []
    for net, rec in sorted(((gap_table.network_of(r["protocol"]), r) for r in (tables or {}).values()),
                           key=lambda x: x[0] != gap_table.ANM6):  # ANM6-Easy's table first, then in file order
        start, end = gap_table.block_markers(net)
        blocks.append(f"{start}\n{gap_table.render_block(rec)}{end}")
    body = "\n\n".join(blocks) if blocks else "No gap table is recorded."
    return f"""## How far from the best achievable: the perfect-foresight AC optimum (issue 15)

Every policy against the perfect-foresight AC-OPF optimum of each test episode, on each registered network, on the
true env. How the optimum is solved, replayed and timed, and the commands that made each table:
`docs/OPTIMAL.md`.

{body}
"""


def _machine(m: dict) -> str:
    """One line naming a record's ``machine`` (:func:`anm_torchrl.provenance.machine_info`)."""
    return (f"{m.get('cpu')}, {m.get('usable_cores')} usable cores, {m.get('memory_gb')} GB, torch threads "
            f"{m.get('torch_threads')}, {m.get('platform')}")


def write_results_md(res: dict, figs: dict, path: str | Path, run_info: dict) -> Path:
    """Render the template with the results and write it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    machine = _machine(run_info.get("machine", {}))
    v = run_info.get("versions", {})
    claims = []
    for text, fn in CLAIMS:
        try:
            what, verdict = fn(res)
        except Exception as err:  # noqa: BLE001
            what, verdict = f"error: {err}", "not measured"
        claims.append(f"| {text} | {what} | **{verdict}** |")
    n_updates = len(run_info.get("updates", []))
    updates = f"; {n_updates} later run{'s' if n_updates != 1 else ''} merged in" if n_updates else ""
    prov = [{"experiment": k, "status": v.get("status"), "command": f"`{portable_command(run_info.get('command'))}`",
             "date": run_info.get("date"), "git commit": (v.get("git_commit") or v_commit)[:7],
             "wall_s": v.get("wall_s")} for k, v in run_info.get("experiments", {}).items()
            for v_commit in [str((run_info.get("versions") or {}).get("git_commit"))]]
    for u in run_info.get("updates", []):  # a later merged run replaces the rows of the experiments it re-ran
        prov = [r for r in prov if r["experiment"] not in u["experiments"]] + [
            {"experiment": k, "status": e.get("status"), "command": f"`{portable_command(u['command'])}`", "date": u["date"],
             "git commit": str(e.get("git_commit") or (u.get("versions") or {}).get("git_commit"))[:7],
             "wall_s": e.get("wall_s")} for k, e in u["experiments"].items()]
    md = TEMPLATE.format(provenance=md_table(prov, ["experiment", "status", "command", "date", "git commit",
                                                  "wall_s"], {"wall_s": ".0f"}),
                         command=run_info.get("command", "python recipes/reproduce.py"), date=run_info.get("date"),
                         updates=updates, records_where=res.get("records_dir") or "results/reproduction/",
                         preset=run_info.get("preset"), wall=run_info.get("wall_s", 0.0),
                         seeds=run_info.get("seeds"), machine=machine,
                         versions=", ".join(f"{k} {val}" for k, val in v.items() if val),
                         claims_table="\n".join(claims), sections=sections(res, figs, path.parent, machine))
    path.write_text(md)
    return path
