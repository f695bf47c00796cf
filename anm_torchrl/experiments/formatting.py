"""Markdown pieces shared by the results page (:mod:`.report`), README's blocks (:mod:`.readme_blocks`) and the
claims (:mod:`.claims`): table cells, tables, recorded paths made portable (no machine's folders), and the generated
blocks between two HTML-comment markers that the studies rewrite in README and the docs."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any


def fmt(x: Any, spec: str = ".3g") -> str:
    """A table cell: ``–`` for None, floats with ``spec``, anything else as ``str``."""
    if x is None:
        return "–"
    if isinstance(x, float):
        return format(x, spec)
    return str(x)


def md_table(rows: list[dict], cols: list[str], formats: dict[str, str] | None = None) -> str:
    """A Markdown table of ``rows`` (dicts) over ``cols``, cells by :func:`fmt` (``formats``: column -> spec)."""
    formats = formats or {}
    if not rows:
        return "_(no rows)_"
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        out.append("| " + " | ".join(fmt(r.get(c), formats.get(c, ".3g")) for c in cols) + " |")
    return "\n".join(out)


def portable(path: str) -> str:
    """``path`` without this machine's folders: under the artifact home as ``$ANM_TORCHRL_HOME/...``, under the
    repository relative to it, else only its last two parts below the top-level folder (``/tmp/run`` -> ``.../run``:
    the top-level folder is this machine's, e.g. ``/tmp``)."""
    from anm_torchrl.paths import artifact_home

    p = Path(path)
    for root, name in ((artifact_home(), "$ANM_TORCHRL_HOME"), (Path(__file__).resolve().parents[2], ".")):
        try:
            return f"{name}/{p.resolve().relative_to(root.resolve())}"
        except ValueError:
            continue
    tail = p.parts[2:][-2:]
    return ".../" + "/".join(tail) if tail else "..."


def portable_command(cmd: str) -> str:
    """A recorded command line or message with its absolute paths made portable (:func:`_portable`)."""
    return re.sub(r"(?<![\w.])(/(?:[\w.\-]+/)*[\w.\-]+)", lambda m: portable(m.group(1)), str(cmd))


def marked_block(start: str, end: str) -> re.Pattern:
    """A page's generated block between the markers ``start`` and ``end``: groups (``start`` and its newline, the
    body, ``end``)."""
    return re.compile(f"({re.escape(start)}\n)(.*?)({re.escape(end)})", re.S)


def replace_marked_blocks(pages: list[str | Path], start: str, end: str, body: str) -> None:
    """Replace the body of the ``start`` ... ``end`` block of every page with ``body``. Every page is checked for the
    block before any is written, so no page is left half-updated; each is written atomically.

    Raises:
        ValueError: the pages without the block, named (nothing is written).
    """
    from anm_torchrl.artifacts import atomic_write

    block = marked_block(start, end)
    texts = {Path(p): Path(p).read_text() for p in pages}
    missing = [str(p) for p, text in texts.items() if not block.search(text)]
    if missing:
        raise ValueError(f"{', '.join(missing)}: no {start} ... {end} block")
    for path, text in texts.items():
        atomic_write(path, block.sub(lambda m: m.group(1) + body + m.group(3), text).encode())
