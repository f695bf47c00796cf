"""The committed records: ``results/<study>/`` folders and their index ``results/INDEX.json``.

The index lists every record by study, with the command that makes it, the claim it backs and ``was``, the path it
had before the study folders. Records are history and never rewritten, so those written before the folders name
their old paths (a gap table's ``record``, its PPO rows' ``file``, a payoff part's ``file``); renderers show the
current path through :func:`current_path`.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "results"
INDEX = RESULTS / "INDEX.json"
REPRODUCTION, PAYOFF, GAP = "reproduction", "payoff", "gap"  # the studies recipes/reproduce.py renders pages from


def study_dir(study: str, root: str | Path = RESULTS) -> Path:
    """The folder of ``study`` under ``root`` (default the committed ``results/``)."""
    return Path(root) / study


@functools.lru_cache(maxsize=1)
def _moved() -> dict[str, str]:
    if not INDEX.is_file():
        return {}
    index = json.loads(INDEX.read_text())
    return {e["was"]: e["file"] for s in index["studies"].values() for e in s["records"] if e.get("was")}


def current_path(path: str) -> str:
    """Where the record a path names lives now: an old ``results/<file>`` path as the index moved it, anything
    else unchanged (a leading ``./`` is dropped first)."""
    p = str(path)
    p = p[2:] if p.startswith("./") else p
    return _moved().get(p, p)


def load_published(root: str | Path = RESULTS) -> dict[str, dict]:
    """The records the published pages render from, keyed by name: the reproduction's (``run`` included), the
    payoff study's, and the gap tables under ``"optimal_gap_tables"`` (file stem -> record)."""
    from anm_torchrl.experiments.io import load_results, read_json

    root = Path(root)
    out = load_results(study_dir(REPRODUCTION, root)) if study_dir(REPRODUCTION, root).is_dir() else {}
    if study_dir(PAYOFF, root).is_dir():
        out.update({k: v for k, v in load_results(study_dir(PAYOFF, root)).items() if k != "run"})
    tables = sorted(study_dir(GAP, root).glob("optimal_gap_table*.json"))
    out["optimal_gap_tables"] = {f.stem: read_json(f) for f in tables}
    return out
