"""The one place a network becomes a simulator: :func:`simulator`.

A network is given as a registered name (:func:`anm_torchrl.networks.list_networks`), a registered
:class:`~anm_torchrl.networks.case.NetworkCase`, or a user's gym-anm network dict with its profiles. Every
path goes through gym-anm's checks (:mod:`anm_torchrl.networks.validation`) and gym-anm's defaults, so that an
env, a dataset and a surrogate given the same network get the same simulator, and hence the same identity keys
(:mod:`anm_torchrl.grid.identity`) under which their artifacts are saved and looked up.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

from anm_torchrl.grid.identity import network_key
from anm_torchrl.grid.simulator import GridSimulator
from anm_torchrl.networks.case import NetworkCase
from anm_torchrl.networks.registry import builtin_networks, get_network
from anm_torchrl.networks.user import DEFAULT_CONSTANTS
from anm_torchrl.networks.validation import check_reward_args, validate_network, validate_profiles

_UNSET = object()  # "not given": a registered case's constant, or gym-anm's default (None means +inf clipping)


def simulator(network: str | NetworkCase | dict, load_p=None, gen_p_max=None, *, delta_t=_UNSET, gamma=_UNSET,
              lamb=_UNSET, costs_clipping=_UNSET, device=None, backend: str = "auto",
              next_vars: Callable | None = None, linear_solver: str = "auto",
              profile_clip_level: int | None = None) -> GridSimulator:
    """The :class:`GridSimulator` of a network.

    Args:
        network: a registered name, a registered :class:`NetworkCase`, or a gym-anm network dict (``None`` / NaN
            where gym-anm allows a missing value).
        load_p: (T, n_load) MW, loads in device-id order; required with a dict, optional with a registered
            network (replaces its profile).
        gen_p_max: (T, n_gen) MW, non-slack generators in device-id order; as ``load_p``.
        delta_t, gamma, lamb, costs_clipping: env constants (h; discount; penalty factor; clipping of |ΔE| and
            λΦ, ``None`` entries meaning +inf). Not given: the registered case's, or gym-anm's defaults
            (:data:`DEFAULT_CONSTANTS`) for a dict.
        device: torch device (None: CPU).
        backend: ``"auto"``, ``"numba"`` or ``"torch"`` (:func:`anm_torchrl.grid.backends.get_backend`).
        next_vars: optional batched exogenous-variable hook (``GridSimulator``'s ``next_vars_hook``).
        linear_solver: the numba backend's Newton step (``GridSimulator``).
        profile_clip_level: the logging level of the line naming clipped profile entries (None: INFO for a
            shipped network's own profiles, WARNING otherwise).

    Raises:
        ValueError: an unknown name (listing the registered ones), a dict without both profiles, another type,
            or a network, profile or constant gym-anm would reject (naming what is wrong).
    """
    if isinstance(network, str):
        network = get_network(network)
    shipped = False  # a shipped network's own profiles: their known clipping is logged at INFO, not WARNING
    # the clipping line names whose profiles it means: a run may build another network's simulator (is_anm6)
    source = "the network's profiles"
    if isinstance(network, NetworkCase):
        case = network
        source = f"the profiles of network {case.name!r}"
        shipped = case.name in builtin_networks() and load_p is None and gen_p_max is None
        defaults = {"delta_t": case.delta_t, "gamma": case.gamma, "lamb": case.lamb,
                    "costs_clipping": case.costs_clipping}
        network = case.network
        load_p = case.load_p if load_p is None else load_p
        gen_p_max = case.gen_p_max if gen_p_max is None else gen_p_max
    elif isinstance(network, dict):
        defaults = DEFAULT_CONSTANTS
        if load_p is None or gen_p_max is None:
            raise ValueError("a network dict needs its profiles: load_p= (T, n_load) and gen_p_max= (T, n_gen) MW")
    else:
        raise ValueError(f"network must be a registered name, a NetworkCase or a gym-anm network dict, got "
                         f"{type(network).__name__}")
    given = {"delta_t": delta_t, "gamma": gamma, "lamb": lamb, "costs_clipping": costs_clipping}
    c = {k: defaults[k] if v is _UNSET else v for k, v in given.items()}
    net = validate_network(network)
    load_p, gen_p_max = validate_profiles(net, load_p, gen_p_max)
    clip = check_reward_args(c["delta_t"], c["gamma"], c["lamb"], c["costs_clipping"])
    if next_vars is not None and not callable(next_vars):
        raise ValueError(f"next_vars must be callable, got {next_vars!r}")
    return GridSimulator.from_tables(net, load_p, gen_p_max, float(c["delta_t"]), float(c["gamma"]),
                                     float(c["lamb"]), clip, device=device, backend=backend,
                                     next_vars_hook=next_vars, linear_solver=linear_solver,
                                     profile_clip_level=(profile_clip_level if profile_clip_level is not None
                                                         else logging.INFO if shipped else logging.WARNING),
                                     profile_source=source)


def action_labels(sim: GridSimulator) -> list[str]:
    """One label per action entry, in the action vector's order: ``"P of device 3"`` (generators' P and Q, then
    storage units' P and Q; devices named by DEV_ID)."""
    ids = sim.net.dev[:, 0].long().tolist()
    return [f"{q} of device {ids[i]}" for q, rows in (("P", sim.gen_idx), ("Q", sim.gen_idx), ("P", sim.des_idx),
                                                    ("Q", sim.des_idx)) for i in rows.tolist()]


def _box_faults(sim: GridSimulator) -> tuple[list[str], list[str]]:
    """The action entries with an infinite bound, each as ``"<label> ([low, high] MW/MVAr)"``, and those whose range
    is a single value (or empty), each as ``"<label> (low MW/MVAr)"``; from one read of the bounds and labels."""
    import torch

    low, high = sim.action_bounds()
    labels = action_labels(sim)
    unbounded = [f"{labels[j]} ([{low[j].item():g}, {high[j].item():g}] MW/MVAr)"
                 for j in (~torch.isfinite(low) | ~torch.isfinite(high)).nonzero().flatten().tolist()]
    flat = [f"{labels[j]} ({low[j].item():g} MW/MVAr)" for j in (high <= low).nonzero().flatten().tolist()]
    return unbounded, flat


def unbounded_actions(sim: GridSimulator) -> list[str]:
    """The action entries with an infinite bound (an unset PMAX, ...), each as ``"<label> ([low, high] MW/MVAr)"``;
    empty for a bounded action box (what a trained policy's ``TanhNormal`` and a uniform draw need)."""
    return _box_faults(sim)[0]


def single_value_actions(sim: GridSimulator) -> list[str]:
    """The action entries whose range is a single value (QMIN = QMAX, PMIN = PMAX), each as
    ``"<label> (value MW/MVAr)"``: a trained policy writes them at that value and chooses the others."""
    return _box_faults(sim)[1]


def check_controllable(network: str | NetworkCase) -> GridSimulator:
    """Refuse a network a policy cannot be trained for, before a controller is trained for it: nothing to control
    (the slack and loads only, or every action's range a single value), or an action whose range is unbounded (an
    unset PMAX: the ``TanhNormal`` would give NaN actions). An action whose range is a single value (a storage unit
    without reactive power, QMIN = QMAX) is written at that value by every trained policy
    (:class:`~anm_torchrl.training.distributions.PartlyFixedTanhNormal`).

    Returns:
        The network's simulator (built for the checks; a caller needs not build it again).

    Raises:
        ValueError: naming the network and what it lacks (or :func:`simulator`'s error for an invalid one).
    """
    sim = simulator(network)
    name = network.name if isinstance(network, NetworkCase) else network
    if sim.action_dim == 0:
        raise ValueError(f"network {name!r} has no controllable device (a generator other than the slack, or a "
                         "storage unit): a policy would have no action to take")
    unbounded, flat = _box_faults(sim)
    if unbounded:  # a TanhNormal between infinite bounds gives NaN actions
        raise ValueError(f"network {name!r}: the action range of {', '.join(unbounded)} is unbounded; a trained "
                         "policy acts in a bounded box (give the device finite PMIN/PMAX and QMIN/QMAX)")
    if len(flat) == sim.action_dim:
        raise ValueError(f"network {name!r}: the action range of every controllable device is a single value "
                         f"({', '.join(flat)}): a policy would have no action to choose")
    return sim


@functools.lru_cache(maxsize=1)
def _anm6_key() -> str:
    from anm_torchrl.networks.registry import ANM6_EASY

    # built only to compare keys: its profiles' clipping line would read as if about the user's network
    return network_key(simulator(ANM6_EASY, profile_clip_level=logging.DEBUG))


def is_anm6(sim: GridSimulator) -> bool:
    """Whether ``sim`` runs ANM6-Easy's network (its tables, number of time steps and reward constants; its
    profiles may differ)."""
    if sim is None:
        raise ValueError("sim is required: pass anm_torchrl.networks.simulator(<network>)")
    from anm_torchrl.networks.registry import ANM6_EASY

    # another bus count is not ANM6-Easy: its simulator (and its profiles' clipping line) is not built for it
    return sim.net.y_bus.shape[0] == get_network(ANM6_EASY).n_bus and network_key(sim) == _anm6_key()
