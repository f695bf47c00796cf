"""Results files of the experiments: JSON (with machine info, versions, seeds, wall time) and CSV.

Every experiment writes ``<out_dir>/<name>.json`` holding ``{"name", "status", "reason", "data", "meta"}``:

* ``status``: ``"ok"``, ``"partial"`` (some pieces not available; see ``data["not_available"]``),
  ``"not available"`` (a dependency — a surrogate, a recipe, a module written elsewhere — is missing) or
  ``"error"`` (the experiment raised; ``reason`` holds the message, the traceback is in ``meta``);
* ``meta``: machine, versions, seeds, configuration and wall time of that experiment.

Tables that the plots and ``docs/RESULTS.md`` use are also written as CSV next to the JSON.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from anm_torchrl.strict_json import json_text, plain_json

STATUSES = ("ok", "partial", "not available", "error")


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (atomically, creating its folder)."""
    from anm_torchrl.artifacts import atomic_write  # it imports torch; this module is read by torch-free recipes

    return atomic_write(path, json_text(obj, indent=2).encode())


def write_record(out_dir: str | Path, stem: str, record: dict, text: str) -> Path:
    """Write a committed record ``<out_dir>/<stem>.json`` (``indent=1``, the format of ``results/``) and its table
    ``<stem>.md``, each atomically; returns the JSON's path."""
    from anm_torchrl.artifacts import atomic_write

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / f"{stem}.json", (json_text(record, indent=1) + "\n").encode())
    atomic_write(out / f"{stem}.md", text.encode())
    return out / f"{stem}.json"


def read_json(path: str | Path) -> Any:
    """The JSON document at ``path``.

    Raises:
        FileNotFoundError: no file there.
        ValueError: the file is not valid JSON (the message names it).
    """
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}): a truncated or hand-edited record?") from err


def write_csv(path: str | Path, rows: list[dict[str, Any]]) -> Path | None:
    """Write a list of flat dicts as CSV (columns: union of keys, in first-seen order); None if no rows."""
    if not rows:
        return None
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: plain_json(v) for k, v in r.items()})
    return path


def result(name: str, status: str, data: dict | None = None, reason: str | None = None, **meta) -> dict:
    """An experiment's result record (see module docstring)."""
    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}, got {status!r}")
    return {"name": name, "status": status, "reason": reason, "data": data or {}, "meta": meta}


def load_results(out_dir: str | Path) -> dict[str, dict]:
    """Every ``<name>.json`` result record under ``out_dir``, keyed by name (``run.json`` included).

    JSON files without a ``name`` (benchmark tables and other records) are not result records and are skipped.

    Raises:
        ValueError: a file is not valid JSON, or its ``name`` is not its file stem — such a record would shadow
            (or be shadowed by) ``<name>.json`` and a report would render the wrong one.
    """
    out = {}
    for p in sorted(Path(out_dir).glob("*.json")):
        try:
            rec = read_json(p)
        except json.JSONDecodeError as e:
            raise ValueError(f"{p}: not valid JSON ({e}); a result record cannot be read from it") from e
        if not (isinstance(rec, dict) and "name" in rec):
            continue
        if rec["name"] != p.stem:
            raise ValueError(
                f"{p}: its record name is {rec['name']!r}, not the file stem {p.stem!r}; result records in "
                f"{out_dir} are named <name>.json (keep partial or input records under inputs/)"
            )
        out[rec["name"]] = rec
    return out
