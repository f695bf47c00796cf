"""Pure batched torch physics of gym-anm networks (float64, no TorchRL).

``GridSimulator`` and ``Transition`` load on first use, so light modules of this package (``grid.identity``,
read by the network registry) import without torch.
"""

__all__ = ["GridSimulator", "Transition"]


def __getattr__(name: str):
    if name in __all__:
        from anm_torchrl.grid import simulator

        return getattr(simulator, name)
    raise AttributeError(f"module 'anm_torchrl.grid' has no attribute {name!r}")
