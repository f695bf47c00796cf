"""ANM6-Easy data: network tables and the five 96-step time series (gym-anm 2.0.1).

Data plus the gym-anm network dict and profile tables built from it (:func:`network`, :func:`load_p`,
:func:`gen_p_max`; its simulator: ``anm_torchrl.networks.simulator(ANM6_EASY)``); the series are built from their nine pieces (spec §2.2). Units are those of
gym-anm's ``network.py``: MW, MVAr, MWh, p.u. on ``BASE_MVA``; device rows use the column order of
``gym_anm/simulator/components/constants.py``.
"""

from __future__ import annotations

import numpy as np

BASE_MVA = 100.0
DELTA_T = 0.25  # h
GAMMA = 0.995
LAMB = 100.0
COSTS_CLIPPING = (1.0, 100.0)
N_TIME = 96

# BUS_ID, BUS_TYPE (0 slack, 1 PQ), BASE_KV, VMAX, VMIN
BUSES = [
    [0, 0, 132, 1.0, 1.0],
    [1, 1, 33, 1.1, 0.9],
    [2, 1, 33, 1.1, 0.9],
    [3, 1, 33, 1.1, 0.9],
    [4, 1, 33, 1.1, 0.9],
    [5, 1, 33, 1.1, 0.9],
]

# F_BUS, T_BUS, BR_R, BR_X, BR_B, RATE (MVA), TAP, SHIFT (deg)
BRANCHES = [
    [0, 1, 0.0036, 0.1834, 0.0, 32, 1, 0],
    [1, 2, 0.03, 0.022, 0.0, 25, 1, 0],
    [1, 3, 0.0307, 0.0621, 0.0, 18, 1, 0],
    [2, 4, 0.0303, 0.0611, 0.0, 18, 1, 0],
    [2, 5, 0.0159, 0.0502, 0.0, 18, 1, 0],
]

# DEV_ID, BUS_ID, DEV_TYPE (-1 load, 0 slack, 2 renewable, 3 storage), Q/P, PMAX, PMIN, QMAX, QMIN,
# P+, P-, Q+, Q-, SOC_MAX, SOC_MIN, EFF   (NaN = not given)
_ = float("nan")
DEVICES = [
    [0, 0, 0, _, 200, -200, 200, -200, _, _, _, _, _, _, _],
    [1, 3, -1, 0.2, 0, -10, _, _, _, _, _, _, _, _, _],
    [2, 3, 2, _, 30, 0, 30, -30, 20, _, 15, -15, _, _, _],
    [3, 4, -1, 0.2, 0, -30, _, _, _, _, _, _, _, _, _],
    [4, 4, 2, _, 50, 0, 50, -50, 35, _, 20, -20, _, _, _],
    [5, 5, -1, 0.2, 0, -30, _, _, _, _, _, _, _, _, _],
    [6, 5, 3, _, 50, -50, 50, -50, 30, -30, 25, -25, 100, 0, 0.9],
]
del _


def _series(a_const: float, s12: tuple, b_const: float, s23: tuple, c_const: float) -> np.ndarray:
    """Nine-piece daily profile of gym-anm's ``ANM6Easy`` (spec §2.2), float64, shape (96,)."""
    s1 = np.full(25, a_const)
    p12 = np.linspace(*s12, 7)
    s2 = np.full(13, b_const)
    p23 = np.linspace(*s23, 7)
    s3 = np.full(13, c_const)
    out = np.concatenate([s1, p12, s2, p23, s3, p23[::-1], s2, p12[::-1], s1[:4]])
    assert out.shape == (N_TIME,)
    return out


# Raw series in MW, rows: P_load dev1, dev3, dev5, P_max dev2 (PV, raw: holds 31.83 and 36.75), dev4 (wind).
# The PV up-ramp 7.25 -> 36.75 and the wind up-ramp start 14.725 are gym-anm's (likely) typos, kept.
TIME_SERIES_MW = np.stack(
    [
        _series(-1, (-1.5, -4.5), -5, (-4.625, -2.375), -2),
        _series(-4, (-4.75, -9.25), -10, (-11.25, -18.75), -20),
        _series(0, (-3.125, -21.875), -25, (-21.875, -3.125), 0),
        _series(0, (0.5, 3.5), 4, (7.25, 36.75), 30),
        _series(40, (36.375, 14.625), 11, (14.725, 36.375), 40),
    ]
)
TIME_SERIES_DEVICES = (1, 3, 5, 2, 4)


def network() -> dict:
    """The ANM6-Easy network as a gym-anm network dict (float64 arrays, NaN where gym-anm has None)."""
    return {"baseMVA": BASE_MVA, "bus": np.array(BUSES, dtype=np.float64),
            "device": np.array(DEVICES, dtype=np.float64), "branch": np.array(BRANCHES, dtype=np.float64)}


def load_p() -> np.ndarray:
    """Load P profiles (96, 3) MW of devices 1, 3, 5 (device-id order)."""
    return TIME_SERIES_MW[:3].T.copy()


def gen_p_max() -> np.ndarray:
    """Raw generator potential profiles (96, 2) MW of devices 2 (PV) and 4 (wind); the PV column exceeds its
    PMAX at four steps (clipped by the simulator, as gym-anm)."""
    return TIME_SERIES_MW[3:].T.copy()

