"""The *Generative* dataset: scrambled Sobol samples over the free state variables and the action.

Each sample is one independent transition (paper §4.2, "Generative"; Cestero et al.). The Sobol point
``u ∈ [0, 1)^(1 + n_des + 2·action_dim)`` (14 on ANM6-Easy; dimension order below) gives

=============  =================================  ===========================================================
dims           variable                           mapping
=============  =================================  ===========================================================
0              time index t of the state          ``floor(T·u)`` (T = 96 on ANM6-Easy)
1 … n_des      SoC of each storage unit           ``SOC_MIN + u·(SOC_MAX − SOC_MIN)`` MWh
next A         device set-points of the state     uniform over the action box (MW / MVAr)
last A         action                             uniform over the action box (MW / MVAr)
=============  =================================  ===========================================================

The state is made consistent the way :func:`anm_torchrl.grid.reset.random_state` does it: one transition at time ``t``
from the state set-points (loads and potentials of the series, projection onto the feasible sets, power flow
for the slack), after which the SoC entry is set to the Sobol SoC (any SoC is reachable with any DES power).
Points whose *state* power flow does not converge (≈0.6 %) are skipped, so the dataset takes the first
``size`` valid points of the sequence. Each is then labelled by one batched :meth:`GridSimulator.step`; about
0.5 % of those steps are terminal, which the terminal classifier needs.
"""

from __future__ import annotations

import logging

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from anm_torchrl.data.options import check_split_units
from anm_torchrl.data.storage import DEFAULT_FRACTIONS, SPLITS, simulator_settings, split_codes, transition_rows
from anm_torchrl.envs.specs import check_integer
from anm_torchrl.grid import devices as dv
from anm_torchrl.grid.simulator import GridSimulator

log = logging.getLogger(__name__)

def sobol_dims(sim: GridSimulator) -> tuple[str, ...]:
    """Names of the Sobol dimensions (module docstring), e.g. ``("t", "soc", "state_setpoints[6]", "action[6]")``."""
    soc = "soc" if sim.n_des == 1 else f"soc[{sim.n_des}]"
    return ("t", soc, f"state_setpoints[{sim.action_dim}]", f"action[{sim.action_dim}]")


def generate_generative(size: int, seed: int = 0, *, sim: GridSimulator, chunk: int = 8192,
                        fractions=DEFAULT_FRACTIONS, progress: bool = False) -> tuple[TensorDict, dict]:
    """Sample and label ``size`` Sobol transitions.

    Args:
        size: number of transitions, >= 3 (one per split; a ``ValueError`` otherwise).
        seed: seed of the scrambled Sobol engine and of the train/val/test split.
        sim: the simulator (``anm_torchrl.networks.simulator(<network>)``; float64).
        chunk: rows simulated per batch (memory/speed only; the rows do not depend on it beyond float64 round-off).
        fractions: train/validation/test fractions (rows are assigned by a seeded permutation).
        progress: show a progress bar.

    Returns:
        ``(td, meta)``: rows as in :mod:`anm_torchrl.data.storage` and the metadata to store with them.
    """
    check_split_units(check_integer("size", size, low=1), "size")  # one row each for train, validation and test
    check_integer("chunk", chunk, low=1)
    dev, b = sim.net.dev, sim.net.base_mva
    a_low, a_high = sim.action_bounds()
    des = dev[sim.des_idx]
    soc_low, soc_high = des[:, dv.SOC_MIN] * b, des[:, dv.SOC_MAX] * b
    na, nd = sim.action_dim, sim.n_des
    dim = 1 + nd + 2 * na
    engine = torch.quasirandom.SobolEngine(dim, scramble=True, seed=int(seed))
    parts, have, drawn, skipped = [], 0, 0, 0
    bar = tqdm(total=size, desc="generative", unit="rows", disable=not progress)
    while have < size:
        u = engine.draw(chunk, dtype=torch.float64).to(dev.device)
        t = torch.clamp((u[:, 0] * sim.n_time).floor().long(), max=sim.n_time - 1)
        soc = soc_low + u[:, 1:1 + nd] * (soc_high - soc_low)
        setpoints = a_low + u[:, 1 + nd:1 + nd + na] * (a_high - a_low)
        action = a_low + u[:, 1 + nd + na:] * (a_high - a_low)
        tr0 = sim.transition(soc / b, t, setpoints / b)  # SoC before is irrelevant once overwritten below
        tr0.soc = soc / b
        state = sim.build_state(tr0, t)
        ok = tr0.converged
        # the points this chunk gives the dataset: up to its (size - have)-th valid one (the rest are never used)
        valid = ok.nonzero().flatten()
        used = int(valid[size - have - 1]) + 1 if valid.numel() >= size - have else chunk
        drawn, skipped = drawn + used, skipped + int((~ok[:used]).sum())
        state, action = state[ok][: size - have], action[ok][: size - have]
        next_state, tr = sim.step(state, action)
        parts.append(transition_rows(sim, state, action, next_state, tr))
        have += state.shape[0]
        bar.update(state.shape[0])
    bar.close()
    td = torch.cat(parts, 0) if len(parts) > 1 else parts[0]
    gen = torch.Generator().manual_seed(int(seed))
    td.set("split", split_codes(size, fractions, gen))
    n_term = int(td.get("terminated").sum())
    log.info("generative dataset: %d rows from %d Sobol points (%d invalid states skipped), %d terminal steps",
             size, drawn, skipped, n_term)
    meta = {
        "kind": "generative", "size": int(size), "seed": int(seed), "simulator": simulator_settings(sim),
        "generator": {"method": "scrambled Sobol (torch.quasirandom.SobolEngine)", "dims": list(sobol_dims(sim)),
                      "sobol_dim": dim, "chunk": int(chunk), "points_drawn": drawn, "invalid_states_skipped": skipped},
        "splits": {name: int((td.get("split") == code).sum()) for name, code in SPLITS.items()},
        "split_fractions": [float(f) for f in fractions], "split_unit": "row",
        "n_terminal": n_term,
    }
    return td, meta
