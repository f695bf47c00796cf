"""Every command line refuses a count, an index or a duration out of range in its parser, naming the option, before
any work starts (:mod:`anm_torchrl.cli.args`)."""

from __future__ import annotations

import importlib

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
]


@pytest.mark.parametrize("command, option, value, message", BAD, ids=[f"{c}{o}={v}" for c, o, v, _ in BAD])
def test_a_bad_count_is_refused_by_the_parser(command, option, value, message, capsys):
    cli = importlib.import_module(f"anm_torchrl.cli.{command}")
    with pytest.raises(SystemExit) as err:
        cli.main([option, value])
    assert err.value.code == 2  # argparse's usage error: nothing ran
    assert f"argument {option}: {message}" in capsys.readouterr().err


def test_the_types_accept_what_is_in_range():
    from anm_torchrl.cli.args import count, index, positive_float

    assert (count("1"), index("0"), positive_float("0.5")) == (1, 0, 0.5)
