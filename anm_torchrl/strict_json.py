"""JSON for users and tools: valid JSON (RFC 8259) always.

``json.dumps`` writes a NaN or an infinity as a bare ``NaN`` / ``Infinity``, which strict parsers (``jq``,
JavaScript's ``JSON.parse``, Go) refuse; run summaries, metrics, evaluation lines and records are written through
:func:`json_text`, which writes them as ``null``. No torch import: recipes write JSON before torch is loaded.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any


def plain_json(x: Any) -> Any:
    """A JSON-able copy of ``x``: tensors and arrays (anything with ``tolist``) to lists or numbers, NaN and
    infinities to None, paths and other objects to ``str``, mapping keys to ``str``."""
    if isinstance(x, Mapping):
        return {str(k): plain_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain_json(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):
        return plain_json(x.tolist())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, (int, str, bool)) or x is None:
        return x
    return str(x)


def json_text(obj: Any, **dumps_kwargs: Any) -> str:
    """``json.dumps`` of :func:`plain_json` (``obj``), strict: never a bare ``NaN`` / ``Infinity``."""
    return json.dumps(plain_json(obj), allow_nan=False, **dumps_kwargs)
