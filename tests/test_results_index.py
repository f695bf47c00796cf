"""``results/INDEX.json`` lists every committed record exactly once, by study, with its command and claim.

A record added without an index entry, an entry whose file is gone, or a record left at the top level of
``results/`` fails here; so does an old path (``was``) that no longer maps to its record, which the renderers use
to show where a record written before the study folders lives now.
"""

from __future__ import annotations

import json
from pathlib import Path

from anm_torchrl.experiments.records import INDEX, RESULTS, current_path

REPO = Path(__file__).resolve().parents[1]


def _entries() -> list[dict]:
    index = json.loads(INDEX.read_text())
    return [{**e, "study": s} for s, study in index["studies"].items() for e in study["records"]]


def test_every_record_is_indexed_once_under_its_study():
    entries = _entries()
    files = [e["file"] for e in entries]
    assert len(files) == len(set(files)), "a record is indexed twice"
    on_disk = {str(p.relative_to(REPO)) for p in RESULTS.rglob("*")
               if p.is_file() and p.name not in (".gitignore", INDEX.name) and "figures" not in p.parts}
    indexed = {f for f in files if not f.endswith("/figures")}
    assert on_disk - indexed == set(), "records without an index entry"
    assert indexed - on_disk == set(), "index entries without a file"
    assert not [p for p in RESULTS.iterdir() if p.is_file() and p.name not in (".gitignore", INDEX.name)], \
        "records belong in results/<study>/"
    for e in entries:
        assert e["file"].startswith(f"results/{e['study']}/"), e["file"]
        assert e["command"] and e["claim"], e["file"]


def test_old_paths_map_to_their_records():
    entries = [e for e in _entries() if "was" in e]  # records made after the move have no old path
    was = [e["was"] for e in entries]
    assert len(was) == len(set(was))
    for e in entries:
        assert current_path(e["was"]) == e["file"]
        assert current_path("./" + e["was"]) == e["file"]
    assert current_path("results/not_a_record.json") == "results/not_a_record.json"
