"""A user's mistake in any recipe is one line naming it (no traceback), exit status 1, and no run directory.

Each recipe checks its config, network, device and checkpoint inside ``training.recipe_errors.user_errors``
before heavy work; the subprocess tests run the real scripts as a user types them, in an empty folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from anm_torchrl.training.recipe_errors import check_device, remove_hydra_only_dir, user_errors

ROOT = Path(__file__).resolve().parents[1]


def test_user_errors_is_one_line_and_removes_a_hydra_only_dir(tmp_path):
    run_dir = tmp_path / "outputs" / "job" / "2026-12-04" / "10-00-00"
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / "job.log").write_text("")
    with pytest.raises(SystemExit, match=r"^job\.py: size must be an integer >= 1, got 0$"):
        with user_errors("job.py", run_dir):
            raise ValueError("size must be an integer >= 1, got 0")
    assert not (tmp_path / "outputs").exists()  # the empty Hydra levels went with it
    with pytest.raises(SystemExit, match=r"^job\.py: 'x' missing$"):  # a KeyError's message, unquoted twice
        with user_errors("job.py"):
            raise KeyError("'x' missing")
    with pytest.raises(RuntimeError):  # not a user's mistake: the traceback stays
        with user_errors("job.py"):
            raise RuntimeError("a bug")


def test_a_run_dir_with_work_in_it_is_kept(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    remove_hydra_only_dir(run_dir)
    assert (run_dir / "checkpoints").is_dir()


def test_check_device():
    check_device("cpu")
    with pytest.raises(ValueError, match="env.device: 'gpu0' is not a torch device"):
        check_device("gpu0")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="env.device=cuda:0: this torch build .* has no usable CUDA device"):
            check_device("cuda:0")


@pytest.mark.parametrize("recipe, override, message", [
    ("make_dataset", "generative.chunk=0", "generative.chunk must be an integer >= 1, got 0"),
    ("train_surrogate", "network=case34bw", "unknown network 'case34bw'"),
    ("reproduce", "preset.experiments=[nope]", "unknown experiment 'nope'"),
    ("sac", "checkpoint.resume=missing.pt", "checkpoint.resume: no file"),
])
def test_recipe_prints_one_line(recipe, override, message, tmp_path):
    env = {**os.environ, "ANM_TORCHRL_HOME": str(tmp_path / "home"), "HYDRA_FULL_ERROR": "0"}
    out = subprocess.run([sys.executable, str(ROOT / "recipes" / f"{recipe}.py"), override], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 1, out.stderr
    assert "Traceback" not in out.stderr + out.stdout
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{recipe}.py: ") and message in last, last
    assert not (tmp_path / "outputs").exists(), list((tmp_path / "outputs").rglob("*"))
