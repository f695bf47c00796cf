"""Every command line refuses a count, an index or a duration out of range in its parser, naming the option, before
any work starts (:mod:`anm_torchrl.cli.args`)."""

from __future__ import annotations

import importlib
import json

import pytest

#: (command, option, a bad value, what the error says)
BAD = [
    ("bench_evaluation", "--repeats", "0", "must be an integer >= 1, got 0"),
    ("bench_evaluation", "--steps", "2.5", "must be an integer >= 1, got '2.5'"),
    ("bench_sb3", "--num-envs", "0", "must be an integer >= 1, got 0"),
    ("bench_sb3", "--gym-rollouts", "-1", "must be an integer >= 1, got -1"),
    ("bench_surrogates", "--min-time", "nan", "must be a finite number > 0, got nan"),
    ("bench_surrogates", "--min-time", "-2", "must be a finite number > 0, got -2"),
    ("bench_surrogates", "--rounds", "two", "must be an integer >= 1, got 'two'"),
    ("bench_training", "--envs", "0", "must be an integer >= 1, got 0"),
    ("bench_training", "--iterations", "0", "must be an integer >= 1, got 0"),
    ("data_driven_battery", "--n-random", "0", "must be an integer >= 1, got 0"),
    ("gap", "--episodes", "0", "must be an integer >= 1, got 0"),
    ("gap", "--steps", "-5", "must be an integer >= 1, got -5"),
    ("gap", "--stability", "-1", "must be an integer >= 0, got -1"),
    ("gradient_study", "--jobs", "0", "must be an integer >= 1, got 0"),
    ("imitation", "--rounds", "-1", "must be an integer >= 0, got -1"),
    ("imitation", "--labels", "1.5", "must be an integer >= 1, got '1.5'"),
    ("leaderboard", "--threads", "0", "must be an integer >= 1, got 0"),
    ("pinn_gradients", "--rows", "0", "must be an integer >= 1, got 0"),
    ("where_they_differ", "--state", "-1", "must be an integer >= 0, got -1"),
    ("where_they_differ", "--window-days", "0", "must be an integer >= 1, got 0"),
    # the benchmark commands' lists and seeds (tracebacks, or an unnamed option, before)
    ("bench_surrogates", "--batch-sizes", "1,x", "must be an integer >= 1, got 'x'"),
    ("bench_sb3", "--seed", "-1", "must be an integer >= 0, got -1"),
]


@pytest.mark.parametrize("command, option, value, message", BAD, ids=[f"{c}{o}={v}" for c, o, v, _ in BAD])
def test_a_bad_count_is_refused_by_the_parser(command, option, value, message, capsys):
    cli = importlib.import_module(f"anm_torchrl.cli.{command}")
    with pytest.raises(SystemExit) as err:
        cli.main([option, value])
    assert err.value.code == 2  # argparse's usage error: nothing ran
    assert f"argument {option}: {message}" in capsys.readouterr().err


def test_the_types_accept_what_is_in_range():
    from anm_torchrl.cli.args import count, index, int_list, name_list, positive_float

    assert (count("1"), index("0"), positive_float("0.5")) == (1, 0, 0.5)
    assert int_list(1)("1, 256,4096") == [1, 256, 4096] and name_list(("a", "b"))("b,a") == ["b", "a"]


@pytest.mark.parametrize("option, value, message", [
    ("--batch-sizes", "x", "must be an integer >= 1, got 'x'"),
    ("--batch-sizes", "0", "must be an integer >= 1, got 0"),
    ("--backends", "nosuch", "must be comma-separated names among auto, numba, torch, got 'nosuch'"),
    ("--threads", "0", "must be an integer >= 1, got 0"),
])
def test_the_env_benchmark_refuses_bad_options_in_its_parser(option, value, message, capsys):
    """``python -m anm_torchrl.benchmarks.env``: tracebacks (int('x'), num_envs 0, an unknown backend) before."""
    from anm_torchrl.benchmarks import env

    with pytest.raises(SystemExit) as err:
        env.main([option, value])
    assert err.value.code == 2 and f"argument {option}: {message}" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["bench_evaluation", "--network", "nosuch"], "unknown network 'nosuch'"),
    (["where_they_differ", "--state", "99", "--out", "{tmp}/w"], "state 99: the gap record"),
    (["payoff", "{tmp}/missing.json"], "missing.json"),
    # the benchmarks: after the whole measurement (the table lost), or a traceback, before
    (["bench_training", "--envs", "4", "--algorithms", "shac", "--out", "/dev/null/x"], "cannot write there"),
    (["bench_training", "--envs", "4", "--algorithms", "shac", "--override", "env.num_envs=16"],
     "the benchmark sets network, env.num_envs, collector.frames_per_batch itself"),
    (["bench_training", "--envs", "4", "--algorithms", "shac", "--override", "loss.horizon=0"],
     "loss.horizon must be an integer >= 1, got 0"),  # measured horizon 1, labelled 0, before
    (["bench_training", "--envs", "4", "--algorithms", "ppo", "--override", "nosuch=1"], "Could not override"),
    (["bench_surrogates", "--device", "nosuch"], "--device: 'nosuch' is not a torch device"),
    (["bench_sb3", "--num-envs", "1", "--n-steps", "1"], "--num-envs x --n-steps must be at least 2"),
])
def test_a_users_mistake_is_one_line(argv, message, tmp_path):
    """Each command's user errors (a name, an index, a file the library refuses) end in one line naming the command,
    not a traceback (they did, except gap's)."""
    import subprocess
    import sys

    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    proc = subprocess.run([sys.executable, "-m", f"anm_torchrl.cli.{args[0]}", *args[1:]], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith(f"python -m anm_torchrl.cli.{args[0]}: ")
    assert message in proc.stderr


def test_the_env_benchmark_refuses_an_unknown_network_and_writes_nothing(tmp_path):
    """A misspelt --network was a warning, an empty table, exit 0 and an empty record written."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "anm_torchrl.benchmarks.env", "--network", "nosuch", "--out",
                           str(tmp_path / "envnet")], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("python -m anm_torchrl.benchmarks.env: --network: unknown "
                                                           "network 'nosuch'")
    assert list(tmp_path.iterdir()) == []


def test_bench_sb3_writes_a_record_only_where_asked(tmp_path, monkeypatch, capsys):
    """Run at other sizes from the repository root, it replaced the committed results/benchmarks/bench_sb3.json."""
    from anm_torchrl.benchmarks import sb3
    from anm_torchrl.cli import bench_sb3

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sb3, "run", lambda *a, command, **k: {"command": command, "rows": []})
    monkeypatch.setattr(sb3, "table", lambda record: "table")
    bench_sb3.main(["--num-envs", "2"])
    assert not any(tmp_path.iterdir())
    bench_sb3.main(["--num-envs", "2", "--out", "r.json"])
    assert json.loads((tmp_path / "r.json").read_text())["command"] == \
        "python -m anm_torchrl.cli.bench_sb3 --num-envs 2 --out r.json"
