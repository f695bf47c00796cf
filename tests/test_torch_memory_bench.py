"""The torch-backend memory benchmark's rows: one spawned process each, glibc's mmap threshold set for that process
only (the parent's environment is restored), the peak resident set after every step."""

from __future__ import annotations

import os

from anm_torchrl.benchmarks import torch_memory


def test_rows_with_and_without_a_fixed_mmap_threshold(tmp_path, monkeypatch):
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    rec = torch_memory.main(["--n-bus", "12", "--envs", "4", "--modes", "dense", "--mmap-threshold-mib", "0", "8",
                             "--steps", "2", "--out", str(tmp_path / "mem")])
    rows = rec["rows"]
    assert [r["mmap_threshold_mib"] for r in rows] == [None, 8]
    assert [r["malloc_mmap_threshold_env"] for r in rows] == [None, str(8 * 2**20)]  # what the child process saw
    assert all(len(r["peak_rss_mib_per_step"]) == 2 and r["peak_rss_mib"] > 0 for r in rows)
    assert "MALLOC_MMAP_THRESHOLD_" not in os.environ
    table = (tmp_path / "mem.md").read_text()
    assert "| 8 MiB |" in table and "| default |" in table
