"""The transition's backends behind one contract, resolved once by name.

A backend is an object with

- ``name``: its registered name;
- ``unusable(net) -> str | None``: why it cannot run a :class:`~anm_torchrl.grid.network.Network` (``None``: it can);
- ``bind(sim) -> transition``: the transition of a :class:`~anm_torchrl.grid.simulator.GridSimulator`,
  ``transition(soc, p_load, p_pot, setpoints) -> Transition`` (p.u.; the arguments of ``GridSimulator.apply``);
- ``build_state(tr, aux, base_mva)``: the next state (N, state_dim) MW… of a transition (zeros on terminal rows);
- ``output_bounds(low, high)`` and ``env_outputs(state, tr, base_mva, bounds)``: an env step's float32 outputs
  (grid quantities, reward, ``terminated``, and ``observation`` when the backend clips it itself).

``bind`` takes the simulator because the two backends read the network in two forms: ``torch`` its torch tensors
(any device, differentiable), ``numba`` one :class:`~anm_torchrl.grid.constants.TransitionConstants` of NumPy
arrays built once. :data:`BACKENDS` names them; :func:`get_backend` is the one place a name is resolved
(``"auto"``: numba where it can run, else torch). Both give the same transitions to float64 round-off (tested
stage by stage in ``tests/test_backends.py``).
"""

from __future__ import annotations

from anm_torchrl.grid.backends.numba import NumbaBackend
from anm_torchrl.grid.backends.torch import TorchBackend

BACKENDS = {"torch": TorchBackend(), "numba": NumbaBackend()}
AUTO = "auto"


def get_backend(name: str, net=None):
    """The backend registered as ``name``, checked against the network ``net`` when given.

    ``"auto"`` (needs ``net``): ``numba`` when it can run ``net``, else ``torch``.

    Raises:
        ValueError: an unknown name (naming the known ones), or a backend that cannot run ``net`` (saying why).
    """
    if name == AUTO:
        if net is None:
            raise ValueError("backend 'auto' is resolved against a network: pass net=")
        return BACKENDS["numba"] if BACKENDS["numba"].unusable(net) is None else BACKENDS["torch"]
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; known: {[AUTO, *BACKENDS]}")
    backend = BACKENDS[name]
    why = None if net is None else backend.unusable(net)
    if why is not None:
        raise ValueError(f"backend={name!r} cannot run this network: {why}")
    return backend


def list_backends() -> list[str]:
    """Every name :func:`get_backend` accepts."""
    return [AUTO, *BACKENDS]
