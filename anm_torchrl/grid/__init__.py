"""Pure batched torch physics of gym-anm networks (float64, no TorchRL).

``GridSimulator`` and ``Transition`` load on first use, so light modules of this package (``grid.identity``,
read by the network registry) import without torch.
"""

from anm_torchrl.lazy import lazy_exports

__all__ = ["GridSimulator", "Transition"]
__getattr__, __dir__ = lazy_exports(__name__, dict.fromkeys(__all__, "simulator"))
