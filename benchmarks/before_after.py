"""``ANM6Env`` throughput of this tree against an earlier commit, measured interleaved (issue 12, item 2).

Usage (from the repository root)::

    python benchmarks/before_after.py [--rev bef482b] [--worktree /tmp/wt_before]
        [--batch-sizes 1,4096,16384] [--threads 2] [--rounds 7] [--min-time 1.0]
        [--out results/benchmarks/bench_anm6_before_after]

The earlier commit is checked out as a detached git worktree (created if missing). Two worker processes, one
importing each tree (``PYTHONPATH``), build ``ANM6Env(num_envs=B, backend="numba")`` once per batch size and
step it as :mod:`anm_torchrl.benchmarks.env` does (``rand_action`` + ``step_and_maybe_reset``, seeded). The
parent asks them in turn — per round and batch size *before, after* or *after, before* (alternating) — so both
see the same load. Each measurement is ``--min-time`` seconds of steady state; the ratio after / before is
taken per round (wall-clock transitions/s, and CPU seconds per transition from ``time.process_time``, which
load on the other cores affects less) and summarised by its median and range over the rounds. The 1-min load
average is recorded at every measurement. About 1 min on a quiet 2-core machine, 2 min under load 6.

Logs a markdown table (and the load average); ``--out`` writes ``<out>.json`` with the summary and every
measurement. It lives outside the package because it runs a second interpreter on another source tree (the
package itself starts no processes but ``git``); it imports nothing from ``anm_torchrl``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

from anm_torchrl.provenance import machine_info

log = logging.getLogger(__name__)

# The worker runs in either tree, so it uses only what both trees offer (ANM6Env's public API).
_WORKER = r"""
import json, sys, time, torch
torch.set_num_threads(int(sys.argv[1]))
from anm_torchrl.envs import ANM6Env
envs = {}
for line in sys.stdin:
    batch, min_time = json.loads(line)
    if batch not in envs:
        env = ANM6Env(num_envs=batch, seed=0, backend="numba")
        torch.manual_seed(0)
        td = env.reset()
        for _ in range(3):  # lazy initialisation, numba dispatch
            _, td = env.step_and_maybe_reset(env.rand_action(td))
        envs[batch] = [env, td]
    env, td = envs[batch]
    n, w0, c0 = 0, time.perf_counter(), time.process_time()
    while True:
        _, td = env.step_and_maybe_reset(env.rand_action(td))
        n += 1
        wall = time.perf_counter() - w0
        if n >= 3 and wall >= min_time:
            break
    envs[batch][1] = td
    print(json.dumps({"steps": n, "wall": wall, "cpu": time.process_time() - c0}), flush=True)
"""


def ensure_worktree(repo: Path, rev: str, path: Path) -> str:
    """A detached worktree of ``rev`` at ``path`` (created if missing); returns its full commit hash."""
    if not (path / "anm_torchrl").is_dir():
        subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", str(path), rev], check=True,
                       capture_output=True)
    head = subprocess.run(["git", "-C", str(path), "rev-parse", "HEAD"], check=True, capture_output=True, text=True)
    want = subprocess.run(["git", "-C", str(repo), "rev-parse", rev], check=True, capture_output=True, text=True)
    if head.stdout.strip() != want.stdout.strip():
        raise ValueError(f"worktree {path} is at {head.stdout.strip()}, not {rev} ({want.stdout.strip()}); "
                         "remove it or pass another --worktree")
    return head.stdout.strip()


class Worker:
    """A process stepping ``ANM6Env`` from the tree at ``root`` on request."""

    def __init__(self, root: Path, threads: int):
        env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": str(threads)}
        self.proc = subprocess.Popen([sys.executable, "-c", _WORKER, str(threads)], cwd=root, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def measure(self, batch: int, min_time: float) -> dict:
        self.proc.stdin.write(json.dumps([batch, min_time]) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"benchmark worker exited with {self.proc.wait()}")
        r = json.loads(line)
        r.update(batch=batch, rate=batch * r["steps"] / r["wall"], cpu_per_transition=r["cpu"] / (batch * r["steps"]),
                 load1=os.getloadavg()[0])
        return r

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def summarise(records: list[dict], batches: list[int]) -> list[dict]:
    """Per batch size: median (and range) over rounds of after / before, wall-clock and CPU-time based."""
    rows = []
    for b in batches:
        rounds = sorted({r["round"] for r in records if r["batch"] == b})
        wall, cpu, rate = [], [], {"before": [], "after": []}
        for k in rounds:
            pair = {r["tree"]: r for r in records if r["batch"] == b and r["round"] == k}
            wall.append(pair["after"]["rate"] / pair["before"]["rate"])
            cpu.append(pair["before"]["cpu_per_transition"] / pair["after"]["cpu_per_transition"])
            for t in rate:
                rate[t].append(pair[t]["rate"])
        rows.append({"batch": b, "rounds": len(rounds), "before_rate": statistics.median(rate["before"]),
                     "after_rate": statistics.median(rate["after"]), "ratio_wall": statistics.median(wall),
                     "ratio_wall_min": min(wall), "ratio_wall_max": max(wall), "ratio_cpu": statistics.median(cpu),
                     "ratio_cpu_min": min(cpu), "ratio_cpu_max": max(cpu)})
    return rows


def markdown_table(rows: list[dict]) -> str:
    lines = ["| batch | before, transitions/s | after, transitions/s | after / before (wall), median [min, max] "
             "| after / before (CPU time), median [min, max] |", "|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['batch']:,} | {r['before_rate']:,.0f} | {r['after_rate']:,.0f} | {r['ratio_wall']:.2f} "
                     f"[{r['ratio_wall_min']:.2f}, {r['ratio_wall_max']:.2f}] | {r['ratio_cpu']:.2f} "
                     f"[{r['ratio_cpu_min']:.2f}, {r['ratio_cpu_max']:.2f}] |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description="ANM6Env throughput, this tree vs an earlier commit, interleaved")
    parser.add_argument("--rev", default="bef482b", help="the 'before' commit")
    parser.add_argument("--worktree", default="/tmp/wt_before", help="where its worktree lives (created if missing)")
    parser.add_argument("--batch-sizes", default="1,4096,16384")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (and the kernel's pool)")
    parser.add_argument("--rounds", type=int, default=7, help="before/after pairs per batch size")
    parser.add_argument("--min-time", type=float, default=1.0, help="seconds of steady state per measurement")
    parser.add_argument("--out", default=None, help="write <out>.json with every measurement")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.min_time <= 0:
        raise ValueError(f"--rounds must be >= 1 and --min-time > 0, got {args.rounds} and {args.min_time}")
    batches = [int(b) for b in args.batch_sizes.split(",") if b.strip()]
    here = Path(__file__).resolve().parents[1]
    before_commit = ensure_worktree(here, args.rev, Path(args.worktree))
    after_commit = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True,
                                  check=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--", "anm_torchrl"],
                                capture_output=True, text=True, check=True).stdout.strip())
    workers = {"before": Worker(Path(args.worktree), args.threads), "after": Worker(here, args.threads)}
    records, t0 = [], time.time()
    try:
        for b in batches:  # warm-up: env construction, first reset, numba compilation or cache load
            for w in workers.values():
                w.measure(b, 0.2)
        for k in range(args.rounds):
            for i, b in enumerate(batches):
                order = ("before", "after") if (k + i) % 2 == 0 else ("after", "before")
                for tree in order:
                    records.append({"tree": tree, "round": k, **workers[tree].measure(b, args.min_time)})
    finally:
        for w in workers.values():
            w.close()
    rows = summarise(records, batches)
    loads = [r["load1"] for r in records]
    result = {
        "command": "python benchmarks/before_after.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "before": {"rev": args.rev, "commit": before_commit}, "after": {"commit": after_commit, "dirty": dirty},
        "threads": args.threads, "rounds": args.rounds, "min_time_s": args.min_time,
        "machine": {"cpu": machine_info()["cpu"], "cores": os.cpu_count(),
                    "python": platform.python_version()},
        "load1": {"min": min(loads), "median": statistics.median(loads), "max": max(loads)},
        "duration_s": time.time() - t0, "summary": rows, "measurements": records,
    }
    log.info("%s\n\n1-min load average during the run: min %.2f, median %.2f, max %.2f; %.0f s",
             markdown_table(rows), min(loads), statistics.median(loads), max(loads), result["duration_s"])
    if args.out:
        out = Path(args.out).with_suffix(".json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main()
