"""Packages whose public names load on first use (PEP 562), so that their light modules (names, config checks)
import without torch: one helper instead of a hand-written ``__getattr__`` per package."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, homes: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package`` whose public names live in ``homes``
    (name -> its home module, absolute or relative to ``package``); a name is imported from its home on first
    access and then kept in the package's namespace."""

    def __getattr__(name: str) -> Any:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        home = homes[name]
        value = getattr(importlib.import_module(home if home.startswith("anm_torchrl") else f"{package}.{home}"),
                        name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *homes})

    return __getattr__, __dir__
