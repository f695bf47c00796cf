"""A network's identity: every content key the package computes, named by the artifact that uses it.

All keys are sha256 digests of a network's tables (and, for some, its profiles and env constants); a saved
artifact records one and a reader recomputes it, so a changed network never loads a stale artifact. The values
are part of the on-disk formats: committed records, caches and manifests name them, so the bytes hashed and
their order must not change (``tests/test_identity.py`` pins every key of every registered network).

============================  =====  ========================  ===================================================
key                           chars  hashes                    used by
============================  =====  ========================  ===================================================
:func:`transition_key`        64     tables, profiles,         ``ANMEnv.transition_key`` and a model's
                                     Δt, γ, λ, clipping        ``transition_key``: ``SurrogateEnv`` refuses a model
                                                               built for another network or other profiles
:func:`network_key`           16     tables, T, Δt, γ, λ,      the PINN cache folder (``surrogates/pinn/cache``)
                                     clipping (no profiles)    and file header (``surrogates/pinn/io``), regressor
                                                               metadata (``surrogates/regressors/io``), dataset and
                                                               surrogate folders off ANM6-Easy
                                                               (``data.for_network``), dataset metadata
:func:`simulator_fingerprint`  16     device table, Y-bus,      ``dataset.json`` ``simulator.fingerprint``, checked
                                     profiles, rates,          by ``data.load_dataset`` against the simulator
                                     constants (repr)          it is loaded for
:func:`case_key`              64     network dict, profiles,   ``NetworkCase.content_hash`` (a registered case's
                                     constants (JSON)          identity, recorded in import records)
============================  =====  ========================  ===================================================

Each function reads the simulator's public attributes only (duck-typed: no import of the simulator).
"""

from __future__ import annotations

import hashlib
import json

import numpy as np


def hash_arrays(*arrays) -> str:
    """sha256 (hex) of a sequence of arrays / numbers: for each, its dtype, shape and bytes, in order."""
    h = hashlib.sha256()
    for a in arrays:
        # tensors by duck type: importing torch here would make the registry (which needs only case_key) heavy
        a = np.ascontiguousarray(a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def transition_key(sim) -> str:
    """Everything that defines ``sim``'s transitions (64 hex chars): network tables, profiles, Δt, γ, λ, costs
    clipping. A model built for one simulator carries it; ``SurrogateEnv`` compares it with its own."""
    net, br = sim.net, sim.net.branches
    return hash_arrays(net.dev, net.y_bus, net.v_min, net.v_max, br.f_bus, br.t_bus, br.y_series, br.y_shunt,
                       br.tap, br.rate, sim.load_series, sim.p_max_series,
                       [net.base_mva, net.delta_t, sim.gamma, sim.lamb, *sim.costs_clipping])


def network_key(sim) -> str:
    """What a saved surrogate is tied to (16 hex chars): the network tables, the number of time steps and the
    reward constants — not the load and generation profiles, which a surrogate reads from the simulator it is
    loaded on (so one saved model runs on scaled or shifted profiles)."""
    net, br = sim.net, sim.net.branches
    return hash_arrays(net.dev, net.y_bus, net.v_min, net.v_max, br.f_bus, br.t_bus, br.y_series, br.y_shunt,
                       br.tap, br.rate,
                       [sim.n_time, net.base_mva, net.delta_t, sim.gamma, sim.lamb, *sim.costs_clipping])[:16]


def profiles_key(sim) -> str:
    """The load and generation profiles ``sim`` steps through (16 hex chars): what :func:`network_key` leaves out."""
    return hash_arrays(sim.load_series, sim.p_max_series)[:16]


def simulator_fingerprint(sim) -> str:
    """The network tables and time series that define ``sim``'s transitions (16 hex chars), as a dataset
    records them (raw bytes, without dtypes or shapes: the format datasets were written with)."""
    h = hashlib.sha256()
    tensors = [sim.net.dev, sim.net.y_bus.real, sim.net.y_bus.imag, sim.load_series, sim.p_max_series,
               sim.net.branches.rate]
    for t in tensors:
        h.update(np.ascontiguousarray(t.detach().cpu().numpy()).tobytes())
    h.update(repr((sim.gamma, sim.lamb, tuple(sim.costs_clipping), float(sim.net.delta_t),
                   float(sim.net.base_mva))).encode())
    return h.hexdigest()[:16]


def case_key(network: dict, load_p: np.ndarray, gen_p_max: np.ndarray, constants: tuple) -> str:
    """A registered case's identity (64 hex chars): the float64 bytes of its tables and profiles and the JSON
    of its constants ``(delta_t, gamma, lamb, costs_clipping)``."""
    h = hashlib.sha256()
    h.update(np.float64(network["baseMVA"]).tobytes())
    for a in (network["bus"], network["device"], network["branch"], load_p, gen_p_max):
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update(json.dumps(list(constants)).encode())
    return h.hexdigest()
