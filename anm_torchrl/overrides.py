"""Hydra command-line overrides (``HydraConfig.get().overrides.task``) read the one way every recipe reads them."""

from __future__ import annotations

from typing import NamedTuple


class Override(NamedTuple):
    """One parsed override: ``prefix`` ``""``, ``"+"`` (add a key), ``"++"`` (add or set) or ``"~"`` (delete);
    ``key`` the dotted key without its ``@package`` (``"model.actor_cells"``); ``value`` the text after ``=``
    (``""`` for ``~key``)."""

    prefix: str
    key: str
    value: str


def parse_override(item: str) -> Override:
    """``"+model.foo@pkg = 1"`` -> ``Override("+", "model.foo", "1")``: Hydra's grammar for the key side (a
    leading ``+``, ``++`` or ``~``; an optional ``@package`` after the key), the value left as typed (stripped)."""
    text = str(item)
    left, _, value = text.partition("=")
    left = left.strip()
    prefix = next((p for p in ("++", "+", "~") if left.startswith(p)), "")
    key = left[len(prefix):].strip().split("@", 1)[0]
    return Override(prefix, key, value.strip())
