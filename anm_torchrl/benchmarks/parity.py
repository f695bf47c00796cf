"""Parity record: every transition recorded from gym-anm 2.0.1, re-stepped in one batch through our envs.

Usage::

    OMP_NUM_THREADS=1 python -m anm_torchrl.benchmarks.parity --out results/parity/parity [--backends numba,torch]

Fixtures (``tests/fixtures``): ``gym_anm_transitions.npz`` (ANM6-Easy, recorded by
``tests/fixtures/record_gym_anm.py``, stepped through :class:`anm_torchrl.envs.ANM6Env`) and every
``generic_<name>.npz`` (gym-anm's generic ``ANMEnv`` on networks of our own, recorded by
``tests/fixtures/record_generic.py``, stepped through :class:`anm_torchrl.envs.ANMEnv`). Each fixture is loaded
whole, its states set with ``reset(..., set_state=True)``, its actions applied as float32, on each backend.

Writes ``<out>.json`` (per fixture and backend: transitions, terminal transitions, max |Δ state| in MW / MVAr /
MWh, max relative |Δ reward|, identical terminations, max |Δ observation|, bus and device counts, pass flags;
plus command, date, git commit, machine) and ``<out>.md`` (one table). The loaders, env builders and tolerances
here are the ones the parity tests (``tests/test_parity_gym_anm.py``, ``tests/test_parity_generic.py``) use.

Tolerances: next states within 1e-6 (MW / MVAr / MWh: both sides solve the same Newton-Raphson to the same
stopping rule); rewards within 1e-6 relative (1e-9 absolute added for rewards near 0; the env's reward is
float32); identical terminations; observations within two float32 ulps or 1e-6 absolute.

What "equal" means: gym-anm projects set-points with cvxpy's default QP solve, which is inexact on rare rows,
while this package projects exactly. Every row outside a tolerance is re-stepped in gym-anm itself with its
projections solved accurately (:mod:`.gym_anm_replay`, OSQP at 1e-12, polished). A row equal to that replay
within the same tolerances is counted as ``qp_inexact`` (gym-anm's default solve was off, not the model) and
passes; a row that differs from both is a real difference and fails, named in ``mismatch_rows``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from anm_torchrl.benchmarks.gym_anm_replay import generic_network, observation_arg
from anm_torchrl.strict_json import json_text

log = logging.getLogger(__name__)

FIXTURES = Path(__file__).resolve().parents[2] / "tests" / "fixtures"
ANM6_FIXTURE = "gym_anm_transitions"
GENERIC_PREFIX = "generic_"
BACKENDS = ("numba", "torch")
STATE_TOL = 1e-6  # MW / MVAr / MWh
REWARD_RTOL, REWARD_ATOL = 1e-6, 1e-9
OBS_RTOL, OBS_ATOL = 2 * 2.0 ** -23, 1e-6  # two float32 ulps; the state tolerance for quantities near 0
# The constants of the recorder's gym-anm env (tests/fixtures/record_generic.py, ProfileEnv).
GENERIC_ENV_KWARGS = {"delta_t": 0.25, "gamma": 0.995, "lamb": 100, "costs_clipping": (1, 100)}


def fixture_names(folder: str | Path = FIXTURES) -> list[str]:
    """Stems of the parity fixtures present in ``folder``: ``gym_anm_transitions`` and ``generic_*``, sorted."""
    folder = Path(folder)
    names = sorted(p.stem for p in folder.glob(f"{GENERIC_PREFIX}*.npz"))
    if (folder / f"{ANM6_FIXTURE}.npz").exists():
        names.insert(0, ANM6_FIXTURE)
    return names


def load_fixture(name: str, folder: str | Path = FIXTURES) -> dict[str, np.ndarray]:
    """All arrays of ``<folder>/<name>.npz`` (no pickles).

    Raises:
        ValueError: the file does not exist.
    """
    path = Path(folder) / f"{name}.npz"
    if not path.exists():
        raise ValueError(f"parity fixture {name!r}: expected {path}, not found")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def generic_env(d: dict[str, np.ndarray], num_envs: int, backend: str, seed: int = 0):
    """:class:`anm_torchrl.envs.ANMEnv` on a generic fixture's network, profiles and observation."""
    from anm_torchrl.envs import ANMEnv

    return ANMEnv(network=generic_network(d), load_p=d["load_p"], gen_p_max=d["gen_p_max"], num_envs=num_envs,
                  observation=observation_arg(json.loads(str(d["observation"]))), seed=seed, backend=backend,
                  **GENERIC_ENV_KWARGS)


def fixture_env(name: str, d: dict[str, np.ndarray], backend: str, seed: int = 0):
    """The env a fixture is compared through, one env per recorded transition."""
    n = len(d["reward"])
    if name == ANM6_FIXTURE:
        from anm_torchrl.envs import ANM6Env

        return ANM6Env(num_envs=n, device="cpu", seed=seed, backend=backend)
    if name.startswith(GENERIC_PREFIX):
        return generic_env(d, n, backend, seed)
    raise ValueError(f"parity fixture name: expected {ANM6_FIXTURE!r} or {GENERIC_PREFIX}<network>, got {name!r}")


def step_recorded(env, d: dict[str, np.ndarray]):
    """One batched step of every recorded transition: ``reset(state, set_state=True)``, float32 actions.

    Returns:
        The ``"next"`` TensorDict (state (n, S) float64, observation (n, O) float32, reward / terminated (n, 1)).
    """
    from tensordict import TensorDict

    n = len(d["reward"])
    td = env.reset(TensorDict({"state": torch.as_tensor(d["state"])}, [n]), set_state=True)
    td["action"] = torch.as_tensor(d["action"], dtype=torch.float32)
    return env.step(td)["next"]


def reference_observation(d: dict[str, np.ndarray], env) -> np.ndarray:
    """gym-anm's observation of each next state, float32 (n, O).

    Generic fixtures store it (``obs``); the ANM6 fixture does not, and ANM6-Easy's observation is the state
    clipped to its bounds (equal to gym-anm's, ``tests/test_parity_gym_anm.py``).
    """
    if "obs" in d:
        return d["obs"]
    low, high = env.sim.state_bounds()
    return np.clip(d["next_state"], low.numpy(), high.numpy()).astype(np.float32)


def row_mismatch(ref_state: np.ndarray, ref_reward: np.ndarray, ref_terminated: np.ndarray, next_state: np.ndarray,
                 reward: np.ndarray, terminated: np.ndarray) -> np.ndarray:
    """Rows (n,) bool whose next state (n, S), reward (n,) or termination (n,) is outside the tolerances."""
    state_bad = np.abs(next_state - ref_state).max(-1) > STATE_TOL
    reward_bad = np.abs(reward - ref_reward) > REWARD_ATOL + REWARD_RTOL * np.abs(ref_reward)
    return state_bad | reward_bad | (terminated.astype(bool) != ref_terminated.astype(bool))


def compare(d: dict[str, np.ndarray], next_state: np.ndarray, reward: np.ndarray, terminated: np.ndarray,
            accurate: dict[str, np.ndarray] | None = None) -> dict:
    """Differences of one batch of next states (n, S), rewards (n,) and terminations (n,) from a fixture's.

    Args:
        accurate: gym-anm's accurate-QP replay (:func:`anm_torchrl.benchmarks.gym_anm_replay.replay`) of the rows
            outside a tolerance, with their indices under ``"rows"``; None: no replay (any such row fails).

    Returns:
        ``max_abs_state_diff`` (MW / MVAr / MWh), ``argmax_state_entry``, ``max_rel_reward_diff``,
        ``max_abs_reward_diff``, ``terminations_identical`` (all against the recording), ``transitions``,
        ``terminal``; ``qp_inexact_rows`` (outside a tolerance of the recording, within all of them of the
        accurate replay), ``mismatch_rows`` (outside of both, or not replayed), ``max_abs_state_diff_accurate``
        (over the replayed rows, None if none); and the pass flags ``state_ok``, ``reward_ok``
        (``|Δr| <= REWARD_ATOL + REWARD_RTOL |r|``) and ``terminations_ok``, each true where every row is within
        its tolerance of the recording or is QP-inexact.
    """
    ref_s, ref_r, ref_t = d["next_state"], d["reward"], d["terminated"].astype(bool)
    ds = np.abs(next_state - ref_s)
    dr = np.abs(reward - ref_r)
    same = int((terminated.astype(bool) == ref_t).sum())
    n = len(ref_r)
    bad = row_mismatch(ref_s, ref_r, ref_t, next_state, reward, terminated)
    qp_inexact = np.zeros(n, dtype=bool)
    max_accurate = None
    if accurate is not None and len(accurate["rows"]):
        rows = np.asarray(accurate["rows"])
        qp_inexact[rows] = bad[rows] & ~row_mismatch(accurate["next_state"], accurate["reward"],
                                                     accurate["terminated"], next_state[rows], reward[rows],
                                                     terminated[rows])
        max_accurate = float(np.abs(next_state[rows] - accurate["next_state"]).max())
    return {"transitions": n, "terminal": int(ref_t.sum()), "max_abs_state_diff": float(ds.max()),
            "argmax_state_entry": int(ds.max(0).argmax()), "max_rel_reward_diff": float((dr / np.abs(ref_r)).max()),
            "max_abs_reward_diff": float(dr.max()), "terminations_identical": same,
            "qp_inexact_rows": np.flatnonzero(qp_inexact).tolist(),
            "mismatch_rows": np.flatnonzero(bad & ~qp_inexact).tolist(), "max_abs_state_diff_accurate": max_accurate,
            "state_ok": bool(np.all((ds.max(-1) <= STATE_TOL) | qp_inexact)),
            "reward_ok": bool(np.all((dr <= REWARD_ATOL + REWARD_RTOL * np.abs(ref_r)) | qp_inexact)),
            "terminations_ok": bool(np.all((terminated.astype(bool) == ref_t) | qp_inexact))}


def run_fixture(name: str, d: dict[str, np.ndarray], backend: str, replay: bool = True) -> dict:
    """Step a fixture through its env on ``backend`` and compare: :func:`compare` plus observation and sizes.

    ``replay``: re-step the rows outside a tolerance in gym-anm with accurate projections (needs the
    ``gym-anm`` extra; a fixture with no such row imports nothing)."""
    env = fixture_env(name, d, backend)
    t0 = time.perf_counter()
    out = step_recorded(env, d)
    wall = time.perf_counter() - t0
    n = len(d["reward"])
    state, reward, term = (out["state"].numpy(), out["reward"].reshape(n).double().numpy(),
                           out["terminated"].reshape(n).numpy())
    accurate = None
    rows = np.flatnonzero(row_mismatch(d["next_state"], d["reward"], d["terminated"], state, reward, term))
    if replay and len(rows):
        from anm_torchrl.benchmarks.gym_anm_replay import replay as gym_anm_replay  # gym-anm: an extra

        log.info("%s (%s): %d rows outside a tolerance, replayed in gym-anm with accurate projections", name,
                 backend, len(rows))
        accurate = {"rows": rows, **gym_anm_replay(d, rows, anm6=name == ANM6_FIXTURE)}
    row = compare(d, state, reward, term, accurate)
    obs, obs_ref = out["observation"].numpy(), reference_observation(d, env)
    if obs.shape != obs_ref.shape:
        raise ValueError(f"{name}: observation shape {obs.shape}, fixture's {obs_ref.shape}")
    dobs = np.abs(obs.astype(np.float64) - obs_ref.astype(np.float64))
    obs_within = np.all(dobs <= OBS_ATOL + OBS_RTOL * np.abs(obs_ref.astype(np.float64)), axis=-1)
    obs_within[row["qp_inexact_rows"]] = True  # observed from the state the accurate replay confirmed
    row.update({"max_abs_obs_diff": float(dobs.max()), "obs_ok": bool(obs_within.all()),
                "n_bus": int(env.sim.net.n_bus), "n_dev": int(env.sim.net.n_dev), "backend": backend,
                "step_s": round(wall, 3)})
    row["passes"] = row["state_ok"] and row["reward_ok"] and row["terminations_ok"] and row["obs_ok"]
    return row


def _versions() -> dict[str, Any]:
    """Git commit (and whether the tree was dirty) and the versions the record depends on."""
    from anm_torchrl.provenance import versions

    v = versions()
    return {"git_commit": v["git_commit"], "git_dirty": v.get("git_dirty"), "torch": v["torch"],
            "numpy": v["numpy"], "numba": v["numba"], "gym-anm": v["gym-anm"]}


def render_markdown(record: dict) -> str:
    """One markdown table of a parity record, with its provenance in a comment."""
    lines = ["| fixture | buses / devices | backend | transitions | terminal | max \\|Δ state\\| (MW, MVAr, MWh) "
             "| max relative \\|Δ reward\\| | terminations | max \\|Δ observation\\| | QP-inexact rows "
             "| passes |",
             "|---|---|---|---:|---:|---:|---:|---|---:|---:|---|"]
    for name, per_backend in record["fixtures"].items():
        for backend, r in per_backend.items():
            lines.append(f"| {name} | {r['n_bus']} / {r['n_dev']} | {backend} | {r['transitions']:,} | "
                         f"{r['terminal']} | {r['max_abs_state_diff']:.1e} | {r['max_rel_reward_diff']:.1e} | "
                         f"{r['terminations_identical']:,} / {r['transitions']:,} identical | "
                         f"{r['max_abs_obs_diff']:.1e} | {len(r.get('qp_inexact_rows', []))} | "
                         f"{'yes' if r['passes'] else 'NO'} |")
    m = record["machine"]
    lines.append(f"\n<!-- {record['command']}; {record['date']}; commit {record['versions']['git_commit']}; "
                 f"{m['cpu']}, torch {record['versions']['torch']}, gym-anm {record['versions']['gym-anm']}; "
                 f"tolerances: state {STATE_TOL:g}, reward {REWARD_RTOL:g} relative, identical terminations; a "
                 f"QP-inexact row differs from the recording but equals gym-anm replayed with accurate projections "
                 f"-->")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    """CLI: write ``<out>.json`` and ``<out>.md``; returns the record."""
    from anm_torchrl.artifacts import atomic_write
    from anm_torchrl.provenance import machine_info

    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--out", default="results/parity/parity", help="output stem: <out>.json and <out>.md")
    p.add_argument("--fixtures", default=str(FIXTURES), help="folder of the .npz fixtures")
    p.add_argument("--backends", default=",".join(BACKENDS), help="comma-separated, of " + ", ".join(BACKENDS))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    backends = args.backends.split(",")
    unknown = sorted(set(backends) - set(BACKENDS))
    if unknown:
        raise ValueError(f"--backends: expected a subset of {BACKENDS}, got {unknown}")
    names = fixture_names(args.fixtures)
    if not names:
        raise ValueError(f"--fixtures: no {ANM6_FIXTURE}.npz or {GENERIC_PREFIX}*.npz in {args.fixtures}")
    torch.set_num_threads(1)
    fixtures: dict[str, dict] = {}
    for name in names:
        d = load_fixture(name, args.fixtures)
        fixtures[name] = {}
        for backend in backends:
            fixtures[name][backend] = run_fixture(name, d, backend)
            log.info("%s (%s): %s", name, backend, fixtures[name][backend])
    record = {"fixtures": fixtures,
              "tolerances": {"state": STATE_TOL, "reward_rtol": REWARD_RTOL, "reward_atol": REWARD_ATOL,
                             "obs_rtol": OBS_RTOL, "obs_atol": OBS_ATOL},
              "command": "python -m anm_torchrl.benchmarks.parity " + shlex.join(sys.argv[1:] if argv is None
                                                                                 else argv),
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "versions": _versions(), "machine": machine_info()}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out.with_suffix(".json"), (json_text(record, indent=1) + "\n").encode())
    atomic_write(out.with_suffix(".md"), render_markdown(record).encode())
    log.info("wrote %s.json and %s.md", out, out)
    return record


if __name__ == "__main__":
    main()
