"""Random-network fuzzing (issue 25): a valid generated network gives two agreeing backends; a corrupted one a
``ValueError`` naming its table, row and column, before anything is built.

Valid networks: :func:`anm_torchrl.networks.random.generate` (radial and meshed, 5-20 buses, every device type),
stepped from random states with random actions in the box on the numba and torch backends (both solve the same
Newton-Raphson to gym-anm's stopping rule: next states within 1e-6 MW / MVAr / MWh, the parity tolerance).
Corruptions: one field of such a network's raw tables at a time, each a rule gym-anm itself enforces.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from anm_torchrl.networks import simulator as network_simulator
from anm_torchrl.networks.random import generate
from anm_torchrl.networks.validation import validate_network
from anm_torchrl.surrogates.pinn.evaluate import random_transitions


@pytest.mark.parametrize("seed", range(6))
def test_valid_random_networks_agree_across_backends(seed):
    case = generate(100 + seed, n_bus=5 + 3 * seed, meshed=bool(seed % 2))
    sims = {b: network_simulator(case.network, case.load_p, case.gen_p_max, backend=b) for b in ("numba", "torch")}
    state, action = random_transitions(sims["torch"], 128, seed=seed)
    out = {b: sim.step(state, action) for b, sim in sims.items()}
    (s_n, t_n), (s_t, t_t) = out["numba"], out["torch"]
    assert torch.equal(t_n.converged, t_t.converged)
    assert (s_n - s_t).abs().max() <= 1e-6
    torch.testing.assert_close(t_n.reward, t_t.reward, rtol=1e-6, atol=1e-9)


def _raw(seed: int = 2) -> tuple[dict, dict[str, int]]:
    case = generate(seed, n_bus=12, meshed=False)
    net = {k: (np.array(v, dtype=float) if k != "baseMVA" else v) for k, v in case.network.items()}
    kinds = net["device"][:, 2]
    rows = {"load": int(np.flatnonzero(kinds == -1)[0]), "gen": int(np.flatnonzero(np.isin(kinds, (1, 2)))[0]),
            "des": int(np.flatnonzero(kinds == 3)[0])}
    return net, rows


MUTATIONS = {  # name: (change to the raw tables, what the error must name)
    "baseMVA <= 0": (lambda n, r: n.__setitem__("baseMVA", -1.0), "baseMVA"),
    "branch to a missing bus": (lambda n, r: n["branch"].__setitem__((1, 1), 99), "'branch'.*T_BUS"),
    "device on a missing bus": (lambda n, r: n["device"].__setitem__((r["load"], 1), 99), "'device'.*BUS_ID"),
    "device table of 14 columns": (lambda n, r: n.__setitem__("device", n["device"][:, :14]), "'device'.*15 columns"),
    "SOC_MIN > SOC_MAX": (lambda n, r: n["device"].__setitem__((r["des"], 13), n["device"][r["des"], 12] + 1),
                          "'device'.*SOC_MAX"),
    "PMIN > PMAX": (lambda n, r: n["device"].__setitem__((r["gen"], 5), n["device"][r["gen"], 4] + 1),
                    "'device'.*PMAX"),
    "negative rating": (lambda n, r: n["branch"].__setitem__((1, 5), -3.0), "'branch'.*RATE"),
    "VMIN > VMAX": (lambda n, r: n["bus"].__setitem__((2, 4), 1.2), "'bus'.*VMAX"),
    "an island": (lambda n, r: n.__setitem__("branch", n["branch"][:-1]), "'branch'.*disconnected"),
    "two slacks": (lambda n, r: n["device"].__setitem__((r["load"], 2), 0), "'device'.*DEV_TYPE"),
    "EFF > 1": (lambda n, r: n["device"].__setitem__((r["des"], 14), 1.5), "'device'.*EFF"),
    "TAP = 0": (lambda n, r: n["branch"].__setitem__((0, 6), 0.0), "'branch'.*TAP"),
    "a producing load": (lambda n, r: n["device"].__setitem__((r["load"], 4), 5.0), "'device'.*PMAX"),
    "duplicate device ids": (lambda n, r: n["device"].__setitem__((1, 0), n["device"][0, 0]), "'device'.*DEV_ID"),
    "NaN bus id": (lambda n, r: n["device"].__setitem__((r["load"], 1), np.nan), "'device'.*BUS_ID"),
}


@pytest.mark.parametrize("name", list(MUTATIONS))
def test_corrupted_network_is_refused_naming_table_and_column(name):
    net, rows = _raw()
    validate_network(net)  # the uncorrupted tables pass
    change, expected = MUTATIONS[name]
    change(net, rows)
    with pytest.raises(ValueError, match=expected):
        validate_network(net)
    with pytest.raises(ValueError, match=expected):  # and nothing is built from them
        network_simulator(net, np.zeros((4, int((net["device"][:, 2] == -1).sum()))),
                          np.zeros((4, int(np.isin(net["device"][:, 2], (1, 2)).sum()))))


def test_missing_values_take_gym_anms_defaults():
    """None / NaN where gym-anm allows a missing value is its default, not an error: BR_R 0 (``Branch``: ``if
    self.r is None: self.r = 0.0``), a load's PMIN -inf (``Load``: ``if self.p_min is None: ... -np.inf``)."""
    net, rows = _raw()
    net["branch"][1, 2] = np.nan
    net["device"][rows["load"], 5] = np.nan
    out = validate_network(net)
    assert out["branch"][1, 2] == 0.0 and out["device"][rows["load"], 5] == -np.inf
